"""A run on a real dask.distributed LocalCluster gives the same output as the local run."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest

from graph.artifact import save_map
from graph.ascii import parse_ascii_map
from mapmatch.io import read_results, write_tracks
from mapmatch.parallel import RunOptions, run_batch
from tests.test_match_cli import DRAWING, make_tracks

distributed = pytest.importorskip("distributed")


def test_local_cluster_equals_local_run_on_partitioned_parquet(tmp_path: Path) -> None:
    m = parse_ascii_map(DRAWING, scale=10)
    map_path = tmp_path / "city.map"
    save_map(m.graph, map_path)
    tracks = make_tracks(m, 6)
    src = tmp_path / "in"
    src.mkdir()
    for i in range(3):  # partitioned Parquet input: one file per partition
        write_tracks(src / f"part-{i}.parquet", tracks[2 * i : 2 * i + 2])
    local = tmp_path / "local.parquet"
    run_batch([src], map_path, local, options=RunOptions(workers=1))
    out_dir = tmp_path / "out"
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=False, dashboard_address=":0"
        ) as cl,
        distributed.Client(cl) as client,
    ):
        s = run_batch([src], map_path, out_dir, options=RunOptions(scheduler=client))
        assert s.partitions == 3 and s.tracks == 6
        again = run_batch([src], map_path, out_dir, options=RunOptions(scheduler=client))
        assert again.skipped == 3 and again.tracks == 0
    parts = sorted(out_dir.glob("part-*.parquet"))
    assert len(parts) == 3
    dask_table = pd.concat([read_results(p) for p in parts], ignore_index=True)
    pd.testing.assert_frame_equal(dask_table, read_results(local))


def test_match_command_with_scheduler_address(tmp_path: Path) -> None:
    from mapmatch.cli import main

    m = parse_ascii_map(DRAWING, scale=10)
    map_path = tmp_path / "city.map"
    save_map(m.graph, map_path)
    tracks = tmp_path / "fleet.csv"
    write_tracks(tracks, make_tracks(m, 4))
    local, remote = tmp_path / "local.csv", tmp_path / "remote.csv"
    assert main(["match", "--map", str(map_path), str(tracks), "-o", str(local), "--workers", "1"]) == 0
    with distributed.LocalCluster(
        n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0"
    ) as cl:
        argv = [
            "match",
            "--map",
            str(map_path),
            str(tracks),
            "-o",
            str(remote),
            "--scheduler",
            cl.scheduler_address,
            "--ubodt",
            "300",  # built once by the run, mapped by the workers
        ]
        assert main([*argv, "--no-progress"]) == 0
    pd.testing.assert_frame_equal(pd.read_csv(local), pd.read_csv(remote))
    assert not (tmp_path / "remote.csv.parts").exists()
