"""CLI conventions: exit statuses, one-line failures, --version, -q/-v everywhere, '-' for stdio,
column options, and no traceback for bad maps, bad paths or Ctrl-C. Real files, real processes."""

from __future__ import annotations

import io
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from graph.artifact import save_map
from graph.ascii import AsciiMap, parse_ascii_map
from mapmatch.cli import EXIT_CONNECT, EXIT_OK, EXIT_PARTIAL, EXIT_USAGE, build_parser, main
from mapmatch.io import write_tracks
from mapmatch.parallel import parts_dir_for
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


@pytest.fixture()
def cross(tmp_path: Path) -> tuple[AsciiMap, Path]:
    m = parse_ascii_map(CROSS, scale=10)
    save_map(m.graph, tmp_path / "cross.map")
    return m, tmp_path / "cross.map"


def fixes_csv(m: AsciiMap, path: Path, *, bad: bool = False, header: str = "") -> Path:
    cols = header or "vehicle_id,time,lat,lon,heading,pos_sigma,speed,distance,gps_valid"
    lines = [cols]
    for f in drive(m, "abs", DriveSpec(speed=8, noise=1.0, seed=1)):
        dist = "" if np.isnan(f.distance) else f"{f.distance:.3f}"
        lines.append(f"car-1,{f.time},{f.lat:.8f},{f.lon:.8f},{f.heading:.2f},4.0,{f.speed},{dist},1")
    if bad:
        lines.append("car-1,10000,95.0,24.9,90,4.0,8,8,1")  # latitude out of range: rejected
    path.write_text("\n".join(lines) + "\n")
    return path


def one_line_error(err: str, command: str) -> None:
    assert err.count("\n") == 1, err
    assert err.startswith(f"mapmatch {command}: error: "), err
    assert "Traceback" not in err


def run_cli(
    *args: str, stdin: bytes | None = None, timeout: float = 120
) -> subprocess.CompletedProcess[bytes]:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run(
        [sys.executable, "-m", "mapmatch", *args], input=stdin, capture_output=True, env=env, timeout=timeout
    )


# ---------------------------------------------------------------------- conventions
def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("mapmatch ") and out.split()[1][0].isdigit()


def test_every_subcommand_takes_q_and_v_and_documents_the_exit_statuses() -> None:
    parser = build_parser()
    subs = next(a for a in parser._actions if a.dest == "command").choices
    assert set(subs) >= {"prep", "replay", "match", "serve", "send", "simulate", "eval", "demo"}
    for name, p in subs.items():
        assert {"-q", "-v"} <= set(p._option_string_actions), name
        assert "exit status:" in p.format_help() and "cannot connect" in p.format_help(), name
    args = parser.parse_args(["replay", "--map", "m", "f.csv", "-o", "o.csv", "-vv"])
    assert args.verbose == 2 and args.quiet is False
    args = parser.parse_args(["-v", "send", "f.csv", "-o", "o.csv", "-q"])
    assert args.verbose == 1 and args.quiet is True


# ---------------------------------------------------------------------- replay
@pytest.mark.slow  # several replay processes
def test_replay_exit_statuses(cross: tuple[AsciiMap, Path], tmp_path: Path, capsys) -> None:
    m, map_path = cross
    good, bad = fixes_csv(m, tmp_path / "good.csv"), fixes_csv(m, tmp_path / "bad.csv", bad=True)
    assert main(["replay", "--map", str(map_path), str(good), "-o", str(tmp_path / "o.csv")]) == EXIT_OK
    capsys.readouterr()
    rc = main(["replay", "--map", str(map_path), str(bad), "-o", str(tmp_path / "o2.csv")])
    assert rc == EXIT_PARTIAL
    cap = capsys.readouterr()
    one_line_error(cap.err, "replay")
    assert "1 of" in cap.err and "rejected" in cap.err and "lat" in cap.err
    assert "rejected 1" in cap.out and (tmp_path / "o2.csv").exists()  # done, with the failure in a row
    (tmp_path / "empty.csv").write_text("vehicle_id,time,lat,lon,heading\n")
    assert (
        main(["replay", "--map", str(map_path), str(tmp_path / "empty.csv"), "-o", str(tmp_path / "e.csv")])
        == 1
    )
    assert "no fixes" in capsys.readouterr().err
    rc = main(
        ["replay", "--map", str(map_path), str(tmp_path / "missing.csv"), "-o", str(tmp_path / "m.csv")]
    )
    assert rc == EXIT_USAGE
    one_line_error(capsys.readouterr().err, "replay")


def test_replay_column_options_and_optional_vehicle_and_heading(
    cross: tuple[AsciiMap, Path], tmp_path: Path, capsys
) -> None:
    m, map_path = cross
    src = fixes_csv(m, tmp_path / "fixes.csv")
    ref = tmp_path / "ref.csv"
    assert main(["replay", "--map", str(map_path), str(src), "-o", str(ref)]) == 0
    df = pd.read_csv(src).rename(columns={"time": "clock", "lat": "y", "lon": "x", "speed": "v"})
    renamed = tmp_path / "renamed.csv"
    df.to_csv(renamed, index=False)
    out = tmp_path / "out.csv"
    rc = main(["replay", "--map", str(map_path), str(renamed), "-o", str(out),
               "--time-col", "clock", "--lat-col", "y", "--lon-col", "x", "--speed-col", "v"])  # fmt: skip
    assert rc == 0
    assert out.read_text() == ref.read_text()
    # no vehicle_id and no heading column: one vehicle named after the file, headings unknown
    df.drop(columns=["vehicle_id", "heading"]).to_csv(tmp_path / "car-9.csv", index=False)
    rc = main(["replay", "--map", str(map_path), str(tmp_path / "car-9.csv"), "-o", str(out),
               "--time-col", "clock", "--lat-col", "y", "--lon-col", "x", "--speed-col", "v"])  # fmt: skip
    assert rc == 0
    res = pd.read_csv(out)
    assert set(res["vehicle_id"]) == {"car-9"} and (res["state"] == "on_road").mean() > 0.5
    capsys.readouterr()
    # a missing time column is named, as a missing latitude column is
    rc = main(
        ["replay", "--map", str(map_path), str(renamed), "-o", str(out), "--lat-col", "y", "--lon-col", "x"]
    )
    assert rc == EXIT_USAGE
    err = capsys.readouterr().err
    one_line_error(err, "replay")
    assert "'time'" in err and "clock, y, x" in err


def test_replay_reads_stdin_and_writes_stdout(cross: tuple[AsciiMap, Path], tmp_path: Path) -> None:
    m, map_path = cross
    src = fixes_csv(m, tmp_path / "fixes.csv")
    ref = tmp_path / "ref.csv"
    assert main(["replay", "--map", str(map_path), str(src), "-o", str(ref)]) == 0
    proc = run_cli("replay", "--map", str(map_path), "-", "-o", "-", "--vehicle-id-col", "vehicle_id",
                   stdin=src.read_bytes())  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == ref.read_bytes()
    assert b"fixes of 1 vehicle(s)" in proc.stderr  # the summary goes to stderr
    assert not (Path.cwd() / "-").exists()


# ---------------------------------------------------------------------- send
def test_send_cannot_connect_exits_3(cross: tuple[AsciiMap, Path], tmp_path: Path, capsys) -> None:
    m, _ = cross
    src = fixes_csv(m, tmp_path / "fixes.csv")
    with socket.socket() as s:  # bound, then released: nothing listens there
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    rc = main(
        ["send", "--server", f"127.0.0.1:{port}", "--timeout", "2", str(src), "-o", str(tmp_path / "o.csv")]
    )
    assert rc == EXIT_CONNECT
    err = capsys.readouterr().err
    one_line_error(err, "send")
    assert "UNAVAILABLE" in err and not (tmp_path / "o.csv").exists()


# ---------------------------------------------------------------------- match
GRID = """
a-----------b-----------c
|           |           |
d-----------e-----------f
"""


@pytest.fixture()
def grid(tmp_path: Path) -> tuple[AsciiMap, Path]:
    m = parse_ascii_map(GRID, scale=10)
    save_map(m.graph, tmp_path / "grid.map")
    return m, tmp_path / "grid.map"


def grid_track(m: AsciiMap, name: str, *, far: bool = False) -> Track:
    x0, y0 = m.xy("a")
    x1, _ = m.xy("c")
    xs = np.linspace(x0 + 5, x1 - 5, 12)
    ys = np.full(len(xs), y0 + (5000.0 if far else 0.5))
    ll = np.array([m.lonlat(x, y) for x, y in zip(xs, ys, strict=True)])
    return Track(name, np.arange(len(xs)) * 3.0, ll[:, 1], ll[:, 0])


def match(map_path: Path, *inputs: Path | str, out: Path | str, extra: tuple[str, ...] = ()) -> int:
    return main(
        ["match", "--map", str(map_path), *map(str, inputs), "-o", str(out), "--workers", "1", "-q", *extra]
    )


def test_match_exit_statuses(grid: tuple[AsciiMap, Path], tmp_path: Path, capsys) -> None:
    m, map_path = grid
    good = tmp_path / "good.csv"
    write_tracks(good, [grid_track(m, "v1"), grid_track(m, "v2")])
    assert match(map_path, good, out=tmp_path / "o.geojson") == EXIT_OK
    assert capsys.readouterr().out == ""  # -q: no summary
    lost = tmp_path / "lost.csv"
    write_tracks(lost, [grid_track(m, "v1"), grid_track(m, "far", far=True)])
    assert match(map_path, lost, out=tmp_path / "o.csv") == EXIT_PARTIAL
    err = capsys.readouterr().err
    one_line_error(err, "match")
    assert "12 of 24 point(s) unmatched" in err and "far" in err
    assert match(map_path, lost, out=tmp_path / "o2.csv", extra=("--max-unmatched", "0.6")) == EXIT_PARTIAL
    capsys.readouterr()  # a track entirely unmatched is a failure whatever the threshold


@pytest.mark.parametrize("kind", ["parquet-text-latlon", "header-only-csv", "gpx-without-track"])
def test_match_exits_1_when_nothing_matches(
    grid: tuple[AsciiMap, Path], tmp_path: Path, capsys, kind: str
) -> None:
    _, map_path = grid
    if kind == "parquet-text-latlon":
        src = tmp_path / "t.parquet"
        pd.DataFrame({"id": ["a", "a"], "time": [0.0, 1.0], "lat": ["x", "y"], "lon": ["u", "v"]}).to_parquet(
            src
        )
    elif kind == "header-only-csv":
        src = tmp_path / "t.csv"
        src.write_text("id,time,lat,lon\n")
    else:
        src = tmp_path / "t.gpx"
        src.write_text('<?xml version="1.0"?><gpx version="1.1" creator="t"><wpt lat="60" lon="24"/></gpx>')
    assert match(map_path, src, out=tmp_path / "o.geojson") == EXIT_PARTIAL
    one_line_error(capsys.readouterr().err, "match")


def test_match_missing_time_column_is_named(grid: tuple[AsciiMap, Path], tmp_path: Path, capsys) -> None:
    m, map_path = grid
    src = tmp_path / "t.csv"
    write_tracks(src, [grid_track(m, "v1")])
    pd.read_csv(src).rename(columns={"time": "clock"}).to_csv(src, index=False)
    assert match(map_path, src, out=tmp_path / "o.csv") == EXIT_USAGE
    err = capsys.readouterr().err
    one_line_error(err, "match")
    assert "'time'" in err and "--time-col" in err
    assert match(map_path, src, out=tmp_path / "o.csv", extra=("--time-col", "clock")) == EXIT_OK


def _damaged(map_path: Path, old: bytes, new: bytes) -> Path:
    data = map_path.read_bytes()
    assert old in data and len(old) == len(new)
    out = map_path.with_name("damaged-" + "".join(c for c in new.decode() if c.isalnum()) + ".map")
    out.write_bytes(data.replace(old, new, 1))
    return out


@pytest.mark.parametrize(
    ("old", "new"),
    [(b'"nbytes"', b'"nbytez"'), (b"EPSG:32635", b"EPSG:99635"), (b"RGMAP", b"XXXXX")],
    ids=["manifest-key", "crs", "not-a-map"],
)
def test_match_bad_map_one_line_and_nothing_written(
    grid: tuple[AsciiMap, Path], tmp_path: Path, capsys, old: bytes, new: bytes
) -> None:
    m, map_path = grid
    src = tmp_path / "t.csv"
    write_tracks(src, [grid_track(m, "v1")])
    bad = _damaged(map_path, old, new)
    out = tmp_path / "o.geojson"
    assert match(bad, src, out=out) == EXIT_USAGE
    one_line_error(capsys.readouterr().err, "match")
    assert not out.exists() and not parts_dir_for(out).exists()


def test_bad_map_in_replay_is_one_line(cross: tuple[AsciiMap, Path], tmp_path: Path, capsys) -> None:
    m, map_path = cross
    src = fixes_csv(m, tmp_path / "fixes.csv")
    for old, new in ((b'"nbytes"', b'"nbytez"'), (b"EPSG:32635", b"EPSG:99635")):
        bad = _damaged(map_path, old, new)
        rc = main(["replay", "--map", str(bad), str(src), "-o", str(tmp_path / "o.csv")])
        assert rc == EXIT_USAGE
        one_line_error(capsys.readouterr().err, "replay")
        assert not (tmp_path / "o.csv").exists()


def test_output_under_a_file_is_one_line(grid: tuple[AsciiMap, Path], tmp_path: Path, capsys) -> None:
    m, map_path = grid
    src = tmp_path / "t.csv"
    write_tracks(src, [grid_track(m, "v1")])
    (tmp_path / "afile").write_text("x")
    assert match(map_path, src, out=tmp_path / "afile" / "o.csv") == EXIT_USAGE
    one_line_error(capsys.readouterr().err, "match")


def test_match_stdin_to_stdout(grid: tuple[AsciiMap, Path], tmp_path: Path) -> None:
    m, map_path = grid
    src = tmp_path / "t.csv"
    write_tracks(src, [grid_track(m, "v1"), grid_track(m, "v2")])
    ref = tmp_path / "ref.csv"
    assert match(map_path, src, out=ref) == 0
    proc = run_cli("match", "--map", str(map_path), "-", "-o", "-", "--workers", "1", stdin=src.read_bytes())
    assert proc.returncode == 0, proc.stderr
    got = pd.read_csv(io.BytesIO(proc.stdout))
    want = pd.read_csv(ref)
    pd.testing.assert_frame_equal(got.drop(columns="track_id"), want.drop(columns="track_id"))
    assert b"matched 2 track(s)" in proc.stderr


# ---------------------------------------------------------------------- Ctrl-C
def _startup_seconds() -> float:
    """How long this machine takes to start Python at all (no program can catch a Ctrl-C before)."""
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", "pass"], check=True)
    return time.perf_counter() - t0


def _interruptible() -> None:
    """In the child before exec: SIGINT as a terminal delivers it, even when the tests run in
    a background job (which starts with SIGINT ignored, and Python keeps it so)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _read_until_progress(proc: subprocess.Popen[bytes], *, timeout: float = 300) -> bytes:
    """Read ``proc``'s stderr until its progress bar has counted matched points (the first
    partition done, the rest still to match); what was read, for the final message."""
    assert proc.stderr is not None
    seen = b""
    deadline = time.monotonic() + timeout
    while not re.search(rb"matching: +\d+%\|[^|]*\| *[1-9][\d.]*k?/", seen):
        assert time.monotonic() < deadline, seen
        chunk = os.read(proc.stderr.fileno(), 4096)
        assert chunk, f"stderr closed before any progress (exit {proc.wait()}): {seen!r}"
        seen += chunk
    return seen


@pytest.mark.slow  # three processes started; one matches a partition of 4,000 tracks
@pytest.mark.parametrize("when", ["start-up 0.2 s", "start-up 0.6 s", "matching"])
def test_ctrl_c_at_any_time_is_one_line(grid: tuple[AsciiMap, Path], tmp_path: Path, when: str) -> None:
    """A Ctrl-C during start-up (imports, then reading stdin, a pipe kept open: the run cannot
    end before the signal) or during matching (after the progress bar has counted the first
    partition, with thousands of tracks still to match) ends with the one line and exit 130."""
    m, map_path = grid
    src = tmp_path / "t.csv"
    write_tracks(src, [grid_track(m, f"v{i}") for i in range(4000)])
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    matching = when == "matching"
    cmd = [sys.executable, "-m", "mapmatch", "match", "--map", str(map_path), str(src) if matching else "-",
           "-o", str(tmp_path / "o.csv"), "--workers", "1", "--kernels", "interpreted"]  # fmt: skip
    proc = subprocess.Popen(
        cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
        preexec_fn=_interruptible,
    )  # fmt: skip
    assert proc.stdin is not None
    if matching:
        before = _read_until_progress(proc)
    else:
        proc.stdin.write(src.read_bytes()[:4096])  # part of the input; the pipe stays open
        proc.stdin.flush()
        time.sleep(1.5 * _startup_seconds() + float(when.split()[1]))
        before = b""
    assert proc.poll() is None, "the run ended before the signal"
    proc.send_signal(signal.SIGINT)
    _, rest = proc.communicate(timeout=60)
    err = before + rest
    # 130, or killed by SIGINT (-2) when the signal lands in compiled code and Python re-delivers
    # it at exit; either way the one line, never a traceback
    assert proc.returncode in (130, -signal.SIGINT), err
    assert b"Traceback" not in err and err.decode().strip().endswith("interrupted"), err
    assert not (tmp_path / "o.csv").exists()


def test_exit_statuses_are_in_readme() -> None:
    text = (ROOT / "README.md").read_text()
    section = text.split("## Exit statuses", 1)[1].split("\n## ", 1)[0]
    for code in (EXIT_OK, EXIT_PARTIAL, EXIT_USAGE, EXIT_CONNECT):
        assert f"| {code} |" in section


# ---------------------------------------------------------------------- simulate and prep
@pytest.mark.slow  # simulate processes
def test_simulate_writes_fixes_to_stdout(grid: tuple[AsciiMap, Path], tmp_path: Path) -> None:
    _, map_path = grid
    ref = tmp_path / "ref.csv"
    common = ("simulate", "--map", str(map_path), "--random-route", "--length-km", "0.3", "--seed", "2",
              "--outages", "none")  # fmt: skip
    assert run_cli(*common, "-o", str(ref)).returncode == 0
    proc = run_cli(*common, "-o", "-")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == ref.read_bytes() and proc.stdout.startswith(b"vehicle_id,time,lat,lon")
    assert b"wrote standard output" in proc.stderr  # the summary goes to stderr
    assert not (Path.cwd() / "-").exists()


def test_prep_refuses_dash_with_one_line(cross: tuple[AsciiMap, Path], tmp_path: Path) -> None:
    _, map_path = cross
    for args in (("prep", str(map_path), "-o", "-"), ("prep", "-", "-o", str(tmp_path / "x.map"))):
        proc = run_cli(*args)
        assert proc.returncode == EXIT_USAGE, proc.stderr
        one_line_error(proc.stderr.decode(), "prep")
        assert "'-' is not accepted" in proc.stderr.decode()
    assert not (Path.cwd() / "-").exists() and not (tmp_path / "x.map").exists()
