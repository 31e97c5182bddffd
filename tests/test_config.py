"""The matcher configuration: sections, full names, validation, and the ways to change it (the
CLI's ``--set``, a TOML table, the server's ``[match]`` tables)."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import pytest

from mapmatch.config import BATCH_CONFIG, DEFAULT_CONFIG, MatchConfig
from mapmatch.errors import ConfigError
from service.config import add_arguments, config_from


def test_every_parameter_has_one_full_name_and_no_shorthand() -> None:
    names = [
        f"{sec.name}.{f.name}"
        for sec in dataclasses.fields(MatchConfig)
        for f in dataclasses.fields(getattr(DEFAULT_CONFIG, sec.name))
    ]
    leaves = [n.split(".")[1] for n in names]
    assert len(set(leaves)) == len(leaves), "a field name is used by two sections"
    assert {n.split(".")[0] for n in names} == {"model", "online", "batch", "measurement"}
    with pytest.raises(AttributeError):
        DEFAULT_CONFIG.gps_sigma  # type: ignore[attr-defined]  # noqa: B018


def test_settings_by_full_name_as_the_cli_takes_them() -> None:
    cfg = DEFAULT_CONFIG.with_settings(["online.step_from_corrected=0", " online.node_hold_sigmas = 2.5"])
    assert (cfg.online.step_from_corrected, cfg.online.node_hold_sigmas) == (0.0, 2.5)
    assert DEFAULT_CONFIG.with_settings([]) == DEFAULT_CONFIG
    assert type(DEFAULT_CONFIG.with_settings(["online.max_hypotheses=8"]).online.max_hypotheses) is int
    assert (
        DEFAULT_CONFIG.with_settings(["measurement.min_probability=0.95"]).measurement.min_probability == 0.95
    )
    for bad, says in (
        (["online.step_from_corrected"], "SECTION.FIELD=VALUE"),
        (["online.node_hold_sigmas=wide"], "online.node_hold_sigmas: 'wide' is not a number"),
        (["online.no_such_field=1"], "online.no_such_field"),
        (["nosuch.gps_sigma=1"], "nosuch: unknown section"),
        (["gps_sigma=1"], "did you mean model.gps_sigma"),
        (["online.max_hypotheses=0"], "max_hypotheses"),
    ):
        with pytest.raises(ConfigError, match=says):
            DEFAULT_CONFIG.with_settings(bad)


def test_a_nested_table_changes_sections_and_names_what_is_wrong() -> None:
    cfg = BATCH_CONFIG.updated({"model": {"gps_sigma": 6.0}, "batch": {"gap_time": 300}})
    assert (cfg.model.gps_sigma, cfg.batch.gap_time) == (6.0, 300)
    assert cfg.model.uturn_penalty == BATCH_CONFIG.model.uturn_penalty  # the rest as it was
    wide = DEFAULT_CONFIG.updated({"measurement": {"road_width": {"residential": 7.0}}})
    assert wide.measurement.road_width == (("residential", 7.0),)
    for bad, says in (
        ({"model": {"nope": 1}}, r"match\.model\.nope"),
        ({"modell": {}}, r"match\.modell: unknown section"),
        ({"model": 3}, r"match\.model: expected a table"),
        ({"model": {"gps_sigma": "wide"}}, "gps_sigma must be a finite non-negative number"),
    ):
        with pytest.raises(ConfigError, match=says):
            DEFAULT_CONFIG.updated(bad, prefix="match.")


def _server(tmp_path: Path, toml: str, *flags: str):  # type: ignore[no-untyped-def]
    p = argparse.ArgumentParser()
    add_arguments(p)
    path = tmp_path / "serve.toml"
    path.write_text(toml)
    return config_from(p.parse_args(["--config", str(path), *flags]), {})


def test_the_servers_file_and_flags_set_both_matchers(tmp_path: Path) -> None:
    toml = "[match.model]\ngps_sigma = 6.0\n[match.online]\nturn_window = 40\n[match.batch]\ngap_time = 300\n"
    c = _server(tmp_path, toml)
    assert (c.matcher.model.gps_sigma, c.batch_matcher.model.gps_sigma) == (6.0, 6.0)
    assert c.matcher.online.turn_window == 40 and c.batch_matcher.batch.gap_time == 300
    # each matcher keeps its own defaults where the file says nothing
    assert c.batch_matcher.model.uturn_penalty == BATCH_CONFIG.model.uturn_penalty
    assert c.matcher.model.uturn_penalty == DEFAULT_CONFIG.model.uturn_penalty
    flagged = _server(tmp_path, toml, "--set", "model.gps_sigma=7", "--set", "batch.gap_time=60")
    assert (flagged.matcher.model.gps_sigma, flagged.batch_matcher.batch.gap_time) == (7.0, 60)
    assert config_from(None, {}).matcher == DEFAULT_CONFIG
    for bad, says in (
        ("[match.model]\nnope = 1\n", "match.model.nope"),
        ("match = 3\n", "match must be a table"),
        ("matcher = 3\n", "unknown setting 'matcher'"),
    ):
        with pytest.raises(ConfigError, match=says):
            _server(tmp_path, bad)
    with pytest.raises(ConfigError, match=r"expected SECTION\.FIELD"):
        _server(tmp_path, "", "--set", "gps_sigma=7")
