"""``mapmatch simulate --map-aided`` in process and against a real server, and ``eval --closed``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from graph.artifact import save_map
from graph.ascii import parse_ascii_map
from mapmatch.cli import main
from mapmatch.measurement import AIDED_COLUMNS

GRID = """
a-------b-------c-------d
|       |       |       |
e-------f-------g-------h
|       |       |       |
i-------j-------k-------l
"""


def test_map_aided_simulation_in_process_and_on_a_server_and_its_evaluation(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    from service.config import ServerConfig
    from service.server import start_server

    grid = parse_ascii_map(GRID, scale=25.0)
    mp = str(tmp_path / "grid.map")
    save_map(grid.graph, mp)
    common = [
        "simulate",
        "--map",
        mp,
        "--random-route",
        "--length-km",
        "3",
        "--outages",
        "60:45",
        "--seed",
        "5",
    ]
    assert main([*common, "-o", str(tmp_path / "open.csv"), "--truth", str(tmp_path / "truth.csv")]) == 0
    assert (
        main(["replay", "--map", mp, str(tmp_path / "open.csv"), "-o", str(tmp_path / "open.matched.csv")])
        == 0
    )
    rc = main(
        [
            *common,
            "--map-aided",
            "-o",
            str(tmp_path / "closed.csv"),
            "--matched",
            str(tmp_path / "closed.matched.csv"),
        ]
    )
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "map-aided:" in out and "answers fed back" in out
    server, port = start_server(
        ServerConfig(address="127.0.0.1:0", grace=1.0, reuse_port=False), {"grid": grid.graph}
    )
    try:
        rc = main(
            [*common, "--map-aided", "--server", f"127.0.0.1:{port}", "-o", str(tmp_path / "remote.csv"),
             "--matched", str(tmp_path / "remote.matched.csv")]
        )  # fmt: skip
    finally:
        server.stop(0)
    assert rc == 0
    opened = pd.read_csv(tmp_path / "open.csv")
    closed = pd.read_csv(tmp_path / "closed.csv")
    remote = pd.read_csv(tmp_path / "remote.csv")
    # the same loop whether the matcher runs in process or on the server; not the open loop
    assert list(closed.columns) == list(opened.columns) and len(closed) == len(opened)
    np.testing.assert_allclose(
        remote[["lat", "lon"]].to_numpy(), closed[["lat", "lon"]].to_numpy(), atol=1e-9
    )
    assert np.abs(closed["lat"] - opened["lat"]).max() > 1e-6
    matched = pd.read_csv(tmp_path / "remote.matched.csv")
    assert set(AIDED_COLUMNS) <= set(matched.columns)
    assert matched["aided_usable"].mean() > 0.5 and set(matched["aided_reason"].fillna("")) <= {
        "", "initialising", "settling", "low_probability", "off_road"
    }  # fmt: skip
    rc = main(
        ["eval", "--map", mp, "--truth", str(tmp_path / "truth.csv"), "--fixes", str(tmp_path / "open.csv"),
         "--matched", str(tmp_path / "open.matched.csv"),
         "--closed", str(tmp_path / "closed.csv"), str(tmp_path / "closed.matched.csv")]
    )  # fmt: skip
    out = capsys.readouterr().out
    assert rc == 0
    table = out[out.index("open vs closed loop") :].splitlines()
    rows = {line.split()[0]: line.split() for line in table[2:4]}
    assert set(rows) == {"open", "closed"}
    # outage-end error (third column) smaller in the closed loop
    assert float(rows["closed"][2]) < float(rows["open"][2])


def test_map_aided_against_no_server_is_exit_3(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    grid = parse_ascii_map(GRID, scale=25.0)
    save_map(grid.graph, tmp_path / "grid.map")
    rc = main(
        ["simulate", "--map", str(tmp_path / "grid.map"), "--random-route", "--length-km", "1", "--outages",
         "none", "-o", str(tmp_path / "f.csv"), "--map-aided", "--server", "127.0.0.1:1"]
    )  # fmt: skip
    err = capsys.readouterr().err
    assert rc == 3 and "server 127.0.0.1:1" in err and "Traceback" not in err
