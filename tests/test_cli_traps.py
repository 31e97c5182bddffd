"""A new user's traps, each with a test: sending a drive twice, `replay` as `match`'s sibling
(GPX, hints, stdin), `eval --route` pictures, the offline HTML map in a real browser, `| head`,
log formats, and bounded reading of huge lines and headers. Real files, real processes, a real
server on a loopback port."""

from __future__ import annotations

import csv
import os
import pty
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from graph.artifact import save_map
from graph.ascii import AsciiMap, parse_ascii_map
from mapmatch.cli import EXIT_OK, EXIT_PARTIAL, EXIT_USAGE, main
from mapmatch.io import MAX_COLUMNS, MAX_LINE_BYTES, MAX_QUOTE, write_tracks
from mapmatch.types import Track
from tests.online_helpers import DriveSpec, drive

ROOT = Path(__file__).resolve().parents[1]

CROSS = """
        n
        |
a-------b-------c
        |
        s
"""
HEADER = "vehicle_id,time,lat,lon,heading,pos_sigma,speed,distance,gps_valid"


@pytest.fixture()
def cross(tmp_path: Path) -> tuple[AsciiMap, Path]:
    m = parse_ascii_map(CROSS, scale=10)
    save_map(m.graph, tmp_path / "cross.map")
    return m, tmp_path / "cross.map"


def fixes_lines(m: AsciiMap, vid: str = "car-1", *, swap: bool = False, t0: float = 0.0) -> list[str]:
    out = []
    for f in drive(m, "abs", DriveSpec(speed=8, noise=1.0, seed=1, t0=t0)):
        dist = "" if np.isnan(f.distance) else f"{f.distance:.3f}"
        lat, lon = (f.lon, f.lat) if swap else (f.lat, f.lon)
        out.append(f"{vid},{f.time},{lat:.8f},{lon:.8f},{f.heading:.2f},4.0,{f.speed},{dist},1")
    return out


def write_csv(path: Path, lines: list[str], header: str = HEADER) -> Path:
    path.write_text("\n".join([header, *lines]) + "\n")
    return path


def run_cli(
    *args: str, stdin: bytes | None = None, timeout: float = 180, **env: str
) -> subprocess.CompletedProcess[bytes]:
    e = dict(os.environ, PYTHONPATH=str(ROOT), **env)
    return subprocess.run(
        [sys.executable, "-m", "mapmatch", *args], input=stdin, capture_output=True, env=e, timeout=timeout
    )


def rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


# ---------------------------------------------------------------------- send twice
def test_send_twice_says_what_to_do_and_new_session_or_vehicle_id_fix_it(
    cross: tuple[AsciiMap, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from service.config import ServerConfig
    from service.server import start_server

    m, _ = cross
    # no vehicle column: the vehicle is named after the file
    lines = [x.split(",", 1)[1] for x in fixes_lines(m)]
    src = write_csv(tmp_path / "drive.csv", lines, header=HEADER.replace("vehicle_id,", "", 1))
    config = ServerConfig(address="127.0.0.1:0", grace=1.0, reuse_port=False, batch_processes=0)
    server, port = start_server(config, {"cross": m.graph})
    try:
        send = ["send", "--server", f"127.0.0.1:{port}", str(src)]
        assert main([*send, "-o", str(tmp_path / "1.csv")]) == EXIT_OK
        capsys.readouterr()
        # the same file again: the server still holds vehicle "drive"; its fixes are rejected
        assert main([*send, "-o", str(tmp_path / "2.csv")]) == EXIT_PARTIAL
        err = capsys.readouterr().err
        assert "time: must increase" in err and "--new-session" in err and "--vehicle-id" in err, err
        assert rows(tmp_path / "2.csv")[0]["state"] == "rejected"
        assert main([*send, "-o", str(tmp_path / "3.csv"), "--new-session"]) == EXIT_OK
        assert main([*send, "-o", str(tmp_path / "4.csv"), "--vehicle-id", "other"]) == EXIT_OK
        assert {r["vehicle_id"] for r in rows(tmp_path / "4.csv")} == {"other"}
        # the fresh session answers as the first run did
        assert [r["edge"] for r in rows(tmp_path / "3.csv")] == [r["edge"] for r in rows(tmp_path / "1.csv")]
    finally:
        server.stop(0)


# ---------------------------------------------------------------------- replay as match's sibling
def test_replay_time_going_back_says_what_to_do_and_new_session_restarts(
    cross: tuple[AsciiMap, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    m, map_path = cross
    src = write_csv(tmp_path / "joined.csv", fixes_lines(m) + fixes_lines(m))  # one drive, twice
    assert main(["replay", "--map", str(map_path), str(src), "-o", str(tmp_path / "a.csv")]) == EXIT_PARTIAL
    err = capsys.readouterr().err
    assert "time: must increase" in err and "--new-session" in err, err
    rc = main(["replay", "--map", str(map_path), str(src), "-o", str(tmp_path / "b.csv"), "--new-session"])
    assert rc == EXIT_OK
    states = [r["state"] for r in rows(tmp_path / "b.csv")]
    assert "rejected" not in states and len(states) == 2 * len(fixes_lines(m))
    half = len(states) // 2
    first = [r["edge"] for r in rows(tmp_path / "b.csv")]
    assert first[:half] == first[half:]  # the second drive is matched as afresh


def test_replay_vehicle_id_names_one_vehicle_and_refuses_several(
    cross: tuple[AsciiMap, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    m, map_path = cross
    one = write_csv(tmp_path / "one.csv", fixes_lines(m))
    out = tmp_path / "o.csv"
    assert main(["replay", "--map", str(map_path), str(one), "-o", str(out), "--vehicle-id", "bus 7"]) == 0
    assert {r["vehicle_id"] for r in rows(out)} == {"bus 7"}
    two = write_csv(tmp_path / "two.csv", fixes_lines(m) + fixes_lines(m, "car-2"))
    capsys.readouterr()
    rc = main(
        ["replay", "--map", str(map_path), str(two), "-o", str(tmp_path / "p.csv"), "--vehicle-id", "x"]
    )
    assert rc == EXIT_USAGE and "holds 2" in capsys.readouterr().err
    assert not (tmp_path / "p.csv").exists()


def test_replay_swapped_lat_lon_exits_1_and_explains(
    cross: tuple[AsciiMap, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    m, map_path = cross
    src = write_csv(tmp_path / "swapped.csv", fixes_lines(m, swap=True))
    assert main(["replay", "--map", str(map_path), str(src), "-o", str(tmp_path / "o.csv")]) == EXIT_PARTIAL
    err = capsys.readouterr().err
    assert err.startswith("mapmatch replay: error: nothing matched") and "lat and lon swapped" in err, err


def test_replay_reads_gpx_and_parquet_as_match_does(cross: tuple[AsciiMap, Path], tmp_path: Path) -> None:
    m, map_path = cross
    fixes = drive(m, "abs", DriveSpec(speed=8, noise=1.0, seed=1, t0=1.7e9))
    track = Track(
        "drive",
        np.array([f.time for f in fixes]),
        np.array([f.lat for f in fixes]),
        np.array([f.lon for f in fixes]),
        heading=np.array([f.heading for f in fixes]),
        speed=np.array([f.speed for f in fixes]),
    )
    edges = {}
    for suffix in ("csv", "gpx", "parquet"):
        src = tmp_path / f"drive.{suffix}"
        write_tracks(src, [track])
        out = tmp_path / f"out-{suffix}.csv"
        assert (
            main(["replay", "--map", str(map_path), str(src), "-o", str(out), "--vehicle-id-col", "id"]) == 0
        )
        got = rows(out)
        assert {r["vehicle_id"] for r in got} == {"drive"}
        edges[suffix] = [r["edge"] for r in got]
    assert len(edges["gpx"]) == len(fixes)
    assert edges["gpx"] == edges["csv"] == edges["parquet"]


def test_replay_names_the_stdin_vehicle_stdin(cross: tuple[AsciiMap, Path], tmp_path: Path) -> None:
    m, map_path = cross
    body = "\n".join(["time,lat,lon,heading", *(",".join(x.split(",")[1:5]) for x in fixes_lines(m))])
    proc = run_cli("replay", "--map", str(map_path), "-", "-o", "-", stdin=body.encode())
    assert proc.returncode == 0, proc.stderr
    vids = {line.split(b",")[0] for line in proc.stdout.splitlines()[1:]}
    assert vids == {b"stdin"}


# ---------------------------------------------------------------------- eval --route pictures
def _route_files(m: AsciiMap, tmp_path: Path) -> tuple[Path, Path]:
    import json

    ll = {k: list(m.lonlat(*m.xy(k))) for k in "abcns"}
    truth = tmp_path / "truth.geojson"
    line = {"type": "LineString", "coordinates": [ll["a"], ll["b"], ll["s"]]}
    truth.write_text(json.dumps({"type": "Feature", "properties": {}, "geometry": line}))
    routes = tmp_path / "routes.geojson"
    feat = {"type": "Feature", "properties": {"track_id": "t1", "n_points": 3, "n_unmatched": 0},
            "geometry": {"type": "LineString", "coordinates": [ll["a"], ll["b"], ll["c"]]}}  # fmt: skip
    routes.write_text(json.dumps({"type": "FeatureCollection", "features": [feat]}))
    return truth, routes


def test_eval_route_draws_png_and_html(cross: tuple[AsciiMap, Path], tmp_path: Path) -> None:
    m, map_path = cross
    truth, routes = _route_files(m, tmp_path)
    fixes = write_csv(tmp_path / "fixes.csv", fixes_lines(m, "t1"))
    png, page = tmp_path / "k.png", tmp_path / "k.html"
    rc = main(["eval", "--route", str(truth), "--matched", str(routes), "--map", str(map_path),
               "--fixes", str(fixes), "--png", str(png), "--html", str(page)])  # fmt: skip
    assert rc == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    html = page.read_text()
    for layer in ("true route", "matched route", "fixes", "road graph"):
        assert f'"name": "{layer}"' in html
    assert html.count('"type": "Point"') == len(fixes_lines(m))


def test_eval_route_picture_that_cannot_be_drawn_is_an_error(
    cross: tuple[AsciiMap, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    m, _ = cross
    truth, routes = _route_files(m, tmp_path)
    blocker = tmp_path / "a-file"  # a file where the picture's folder would be
    blocker.write_text("x")
    for flag in ("--png", "--html"):
        out = blocker / f"k{flag.replace('--', '.')}"
        rc = main(["eval", "--route", str(truth), "--matched", str(routes), flag, str(out)])
        err = capsys.readouterr().err.splitlines()
        assert rc == EXIT_USAGE and err[-1].startswith("mapmatch eval: error: "), err
        assert "Traceback" not in "\n".join(err)


# ---------------------------------------------------------------------- offline HTML in a browser
def test_html_map_is_self_contained_and_draws_roads_offline(
    cross: tuple[AsciiMap, Path], tmp_path: Path
) -> None:
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        pytest.skip("needs chromium (Debian: apt-get install chromium) to render the HTML map")
    m, map_path = cross
    truth, routes = _route_files(m, tmp_path)
    page = tmp_path / "k.html"
    assert main(["eval", "--route", str(truth), "--matched", str(routes), "--map", str(map_path),
                 "--html", str(page)]) == 0  # fmt: skip
    html = page.read_text()
    # nothing is fetched from elsewhere: no script or stylesheet by URL, Leaflet inlined
    assert not re.search(r"<script[^>]+src=|<link[^>]+href=", html)
    assert "cdn" not in html.lower() and "leaflet" in html.lower()
    dom = _render(browser, page)  # offline: an unreachable proxy fails any network fetch
    n_roads = len([e for e in range(m.graph.n_edges) if not 0 <= m.graph.edge_reverse[e] < e])
    drawn = re.findall(r'<path[^>]*class="[^"]*mm-road-graph', dom)
    assert len(drawn) == n_roads, (len(drawn), n_roads)
    assert re.search(r'<path[^>]*class="[^"]*mm-true-route', dom)
    assert re.search(r'<path[^>]*class="[^"]*mm-matched-route', dom)
    # the map of a simulated drive (`eval --truth --html`, the demo's match.html) as well
    dom = _render(browser, _drive_page(m, tmp_path / "drive.html"))
    assert len(re.findall(r'<path[^>]*class="[^"]*mm-road-graph', dom)) == n_roads
    assert len(re.findall(r'<path[^>]*class="[^"]*mm-snapped[ "]', dom)) > 10


def _render(browser: str, page: Path) -> str:
    """The DOM of ``page`` after headless Chromium ran its scripts, with no network."""
    proc = subprocess.run(
        [browser, "--headless", "--no-sandbox", "--disable-gpu", "--proxy-server=127.0.0.1:9",
         "--virtual-time-budget=5000", "--dump-dom", page.as_uri()],
        capture_output=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout.decode()


def _drive_page(m: AsciiMap, out: Path) -> Path:
    import pandas as pd

    from mapmatch.plots import draw_html, plot_data

    fixes = drive(m, "abs", DriveSpec(speed=8, noise=1.0, seed=1))
    frame = pd.DataFrame({"time": [f.time for f in fixes], "lat": [f.lat for f in fixes],
                          "lon": [f.lon for f in fixes]})  # fmt: skip
    matched = frame.assign(state="on_road", edge=m.edge("a", "b"))
    route = np.array([m.xy("a"), m.xy("b"), m.xy("s")])
    draw_html(m.graph, plot_data(m.graph, route_xy=route, fixes=frame, matched=matched), out, title="drive")
    return out


# ---------------------------------------------------------------------- | head
def test_output_into_a_closed_pipe_exits_quietly(cross: tuple[AsciiMap, Path], tmp_path: Path) -> None:
    m, map_path = cross
    lines = [x for k in range(60) for x in fixes_lines(m, f"car-{k}")]  # well over a pipe's 64 KiB
    src = write_csv(tmp_path / "fleet.csv", lines)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen(
        [sys.executable, "-m", "mapmatch", "replay", "--map", str(map_path), str(src), "-o", "-"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
    )  # fmt: skip
    assert proc.stdout is not None and proc.stderr is not None
    assert proc.stdout.readline().startswith(b"vehicle_id,")  # as `| head -1`
    proc.stdout.close()
    err = proc.stderr.read().decode()
    rc = proc.wait(timeout=180)
    assert rc in (0, 141), (rc, err)
    assert "Broken pipe" not in err and "error" not in err and "Traceback" not in err, err


# ---------------------------------------------------------------------- log formats
def test_logs_are_text_on_a_terminal_and_json_otherwise() -> None:
    import json
    import logging

    from mapmatch.logs import formatter, resolve_format

    main_fd, tty_fd = pty.openpty()
    try:
        with os.fdopen(tty_fd, "w") as tty:
            assert resolve_format("auto", tty) == "text"
            assert resolve_format("json", tty) == "json"
    finally:
        os.close(main_fd)
    with open(os.devnull, "w") as pipe_like:
        assert resolve_format("auto", pipe_like) == "json"
        assert resolve_format("text", pipe_like) == "text"
    rec = logging.LogRecord("mapmatch.io", logging.INFO, __file__, 1, "reading %s", ("x",), None)
    assert json.loads(formatter("json").format(rec))["message"] == "reading x"
    assert formatter("text").format(rec).endswith("INFO mapmatch.io: reading x")


@pytest.mark.slow  # serve and match processes
def test_log_format_flag_in_a_real_process(cross: tuple[AsciiMap, Path], tmp_path: Path) -> None:
    import json

    m, map_path = cross
    # "latitude"/"longitude" are read as lat/lon and say so at INFO (-v)
    src = write_csv(
        tmp_path / "f.csv", fixes_lines(m), header=HEADER.replace("lat,lon", "latitude,longitude")
    )
    args = ("replay", "--map", str(map_path), str(src), "-o", str(tmp_path / "o.csv"), "-v")
    piped = run_cli(*args)  # stderr is a pipe: JSON lines
    assert piped.returncode == 0, piped.stderr
    recs = [json.loads(x) for x in piped.stderr.decode().splitlines() if x.startswith("{")]
    assert any("latitude" in r["message"] for r in recs), piped.stderr
    text = run_cli(*args, "--log-format", "text")
    assert b"INFO mapmatch.io: reading column 'latitude'" in text.stderr, text.stderr


# ---------------------------------------------------------------------- bounded reading
def _one_line_bounded(proc: subprocess.CompletedProcess[bytes], command: str, filler: str) -> str:
    err = proc.stderr.decode()
    assert proc.returncode == EXIT_USAGE, (proc.returncode, err[-500:])
    assert err.startswith(f"mapmatch {command}: error: ") and err.count("\n") == 1, err[:500]
    assert "Traceback" not in err
    longest = max((len(x) for x in re.findall(f"(?:{re.escape(filler)})+", err)), default=0)
    assert longest <= MAX_QUOTE, longest  # at most 200 characters of the input quoted
    return err


def test_a_header_of_two_million_columns_is_refused(cross: tuple[AsciiMap, Path], tmp_path: Path) -> None:
    _, map_path = cross
    n = 2_000_000
    big = tmp_path / "wide.csv"
    with open(big, "w") as f:
        f.write(",".join(f"c{i}" for i in range(n)) + "\n")
        f.write("1," * (n - 1) + "1\n")
    assert big.stat().st_size > 20e6
    for cmd in ("replay", "match"):
        proc = run_cli(cmd, "--map", str(map_path), str(big), "-o", str(tmp_path / f"{cmd}.csv"))
        err = _one_line_bounded(proc, cmd, ",c")
        assert f"longer than {MAX_LINE_BYTES:,} bytes" in err and "line 1 " in err
        assert not (tmp_path / f"{cmd}.csv").exists()


def test_too_many_columns_is_refused_quoting_200_characters(
    cross: tuple[AsciiMap, Path], tmp_path: Path
) -> None:
    _, map_path = cross
    wide = tmp_path / "wide.csv"
    wide.write_text(",".join(["time", "lat", "lon", *(f"x{i}" for i in range(5000))]) + "\n1,2,3\n")
    proc = run_cli("replay", "--map", str(map_path), str(wide), "-o", str(tmp_path / "o.csv"))
    err = _one_line_bounded(proc, "replay", ",x")
    assert f"5,003 columns, more than the limit of {MAX_COLUMNS:,}" in err


@pytest.mark.parametrize("via", ["file", "stdin"])
def test_a_64_mib_field_is_refused_without_echoing_it(
    cross: tuple[AsciiMap, Path], tmp_path: Path, via: str
) -> None:
    _, map_path = cross
    big = tmp_path / "field.csv"
    with open(big, "wb") as f:
        f.write(b"vehicle_id,time,lat,lon\nv,1,60.1,")
        f.write(b"9" * (64 << 20))
        f.write(b"\nv,2,60.1,24.9\n")
    if via == "file":
        proc = run_cli("replay", "--map", str(map_path), str(big), "-o", str(tmp_path / "o.csv"))
    else:
        proc = run_cli("replay", "--map", str(map_path), "-", "-o", "-", stdin=big.read_bytes())
        assert proc.stdout == b""
    err = _one_line_bounded(proc, "replay", "9")
    assert "line 2 is longer than" in err


def test_a_bad_cell_is_quoted_at_most_200_characters(cross: tuple[AsciiMap, Path], tmp_path: Path) -> None:
    _, map_path = cross
    src = tmp_path / "bad.csv"
    src.write_text("vehicle_id,time,lat,lon\nv,1,60.1," + "z" * 50_000 + "\n")
    proc = run_cli("replay", "--map", str(map_path), str(src), "-o", str(tmp_path / "o.csv"))
    err = _one_line_bounded(proc, "replay", "z")
    assert "not a number on line 2" in err and "more characters" in err


@pytest.mark.parametrize("terminal", [True, False])
def test_serve_logs_text_on_a_terminal_and_json_into_a_pipe(
    cross: tuple[AsciiMap, Path], terminal: bool
) -> None:
    import json
    import select
    import signal

    _, map_path = cross
    main_fd, tty_fd = pty.openpty() if terminal else os.pipe()
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("MAPMATCH_LOG_FORMAT", None)
    proc = subprocess.Popen(
        [sys.executable, "-m", "mapmatch", "serve", "--map", f"cross={map_path}", "--address", "127.0.0.1:0",
         "--grace", "1", "--batch-processes", "0"],
        stdout=subprocess.PIPE, stderr=tty_fd, env=env, text=True,
    )  # fmt: skip
    os.close(tty_fd)
    try:
        assert proc.stdout is not None and "listening on" in proc.stdout.readline()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 0
        out = b""
        while select.select([main_fd], [], [], 2.0)[0]:
            try:
                chunk = os.read(main_fd, 65536)
            except OSError:  # the terminal's other end closed
                break
            if not chunk:
                break
            out += chunk
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        os.close(main_fd)
    lines = [x for x in out.decode().splitlines() if x.strip()]
    assert lines, "serve logged nothing"
    if terminal:
        assert not any(x.lstrip().startswith("{") for x in lines), lines
        assert any(" INFO mapmatch.service: " in x for x in lines), lines
    else:
        assert all(json.loads(x)["logger"].startswith("mapmatch") for x in lines), lines
