"""The matcher configuration: sections, full names, validation, and the ways to change it (the
CLI's ``--set``, a TOML table, the server's ``[match]`` tables)."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import pytest

from mapmatch.config import BATCH_CONFIG, DEFAULT_CONFIG
from mapmatch.errors import ConfigError
from service.config import add_arguments, config_from


def _leaves(section: object, path: str) -> list[str]:
    """Every field's dotted path under ``section``."""
    out = []
    for f in dataclasses.fields(section):  # type: ignore[arg-type]
        v = getattr(section, f.name)
        full = f"{path}.{f.name}" if path else f.name
        out += _leaves(v, full) if dataclasses.is_dataclass(v) else [full]
    return out


def _sections(section: object, path: str) -> dict[str, object]:
    """Every section under ``section`` (itself too) by its dotted path."""
    out = {path: section}
    for f in dataclasses.fields(section):  # type: ignore[arg-type]
        v = getattr(section, f.name)
        if dataclasses.is_dataclass(v):
            out |= _sections(v, f"{path}.{f.name}" if path else f.name)
    return out


def test_every_parameter_has_one_full_name_and_no_shorthand() -> None:
    names = _leaves(DEFAULT_CONFIG, "")
    leaves = [n.rsplit(".", 1)[1] for n in names]
    assert len(set(leaves)) == len(leaves), "a field name is used by two sections"
    assert {n.split(".")[0] for n in names} == {"model", "online", "batch", "measurement", "confidence"}
    assert "online.region.max_hypotheses" in names and "batch.route.max_route_factor" in names
    with pytest.raises(AttributeError):
        DEFAULT_CONFIG.gps_sigma  # type: ignore[attr-defined]  # noqa: B018
    with pytest.raises(AttributeError):
        DEFAULT_CONFIG.online.max_hypotheses  # type: ignore[attr-defined]  # noqa: B018


def test_sections_hold_a_handful_of_fields_each() -> None:
    """Each section holds either sub-sections or at most 16 fields; none is empty."""
    sizes = {}
    for path, sec in _sections(DEFAULT_CONFIG, "").items():
        kinds = [dataclasses.is_dataclass(getattr(sec, f.name)) for f in dataclasses.fields(sec)]  # type: ignore[arg-type]
        assert all(kinds) or not any(kinds), f"{path or 'the root'} mixes fields and sub-sections"
        if not any(kinds):
            sizes[path] = len(kinds)
    assert sizes and all(1 <= n <= 16 for n in sizes.values()), sizes
    assert {"online.region", "online.anchor", "batch.route", "batch.split"} <= set(sizes)
    assert sum(sizes.values()) == len(_leaves(DEFAULT_CONFIG, ""))


def test_settings_by_full_name_as_the_cli_takes_them() -> None:
    cfg = DEFAULT_CONFIG.with_settings(["online.bias.bias_emission=0", " online.stop.node_hold_sigmas = 2.5"])
    assert (cfg.online.bias.bias_emission, cfg.online.stop.node_hold_sigmas) == (0.0, 2.5)
    assert cfg.online.region == DEFAULT_CONFIG.online.region  # the other sub-sections as they were
    assert DEFAULT_CONFIG.with_settings([]) == DEFAULT_CONFIG
    eight = DEFAULT_CONFIG.with_settings(["online.region.max_hypotheses=8"])
    assert eight.online.region.max_hypotheses == 8 and type(eight.online.region.max_hypotheses) is int
    assert (
        DEFAULT_CONFIG.with_settings(["measurement.min_probability=0.95"]).measurement.min_probability == 0.95
    )
    for bad, says in (
        (["online.bias.bias_emission"], "SECTION.FIELD=VALUE"),
        (
            ["online.stop.node_hold_sigmas=wide"],
            "online.stop.node_hold_sigmas: 'wide' is not a number",
        ),
        (
            ["online.no_such_field=1"],
            r"online\.no_such_field: unknown section \(the sections of online are region",
        ),
        (["online.region.max_hypothesis=8"], r"did you mean online\.region\.max_hypotheses\?"),
        (["online.region.no_such_field=1"], r"unknown parameter\(s\): online\.region\.no_such_field"),
        (["nosuch.gps_sigma=1"], "nosuch: unknown section"),
        (["gps_sigma=1"], r"did you mean model\.gps_sigma\?"),
        (["max_hypotheses=8"], r"did you mean online\.region\.max_hypotheses\?"),
        (
            ["online.max_hypotheses=8"],
            r"online\.max_hypotheses: .*did you mean online\.region\.max_hypotheses\?",
        ),
        (
            ["online.stop.max_hypotheses=8"],
            r"online\.stop\.max_hypotheses.*did you mean online\.region\.max_hypotheses",
        ),
        (["online.region=8"], r"online\.region: expected a table"),
        (["model.gps_sigma.x=8"], r"model\.gps_sigma"),
        (["online.region.max_hypotheses=0"], r"online\.region\.max_hypotheses must be at least 1"),
        (["batch.outliers.outlier_lookahead=2"], r"batch\.outliers\.outlier_lookahead must be 0 or 1"),
        (["online.corrections.trail_max=1"], r"online\.corrections\.trail_max must be at least 2"),
        (["online.evidence.turn_sigma=0"], r"online\.evidence\.turn_sigma must be positive"),
        (["online.region.max_hops=1.5"], r"online\.region\.max_hops must be a whole number"),
    ):
        with pytest.raises(ConfigError, match=says):
            DEFAULT_CONFIG.with_settings(bad)


def test_replace_takes_bare_names_and_whole_sections() -> None:
    cfg = DEFAULT_CONFIG.replace(max_hypotheses=16, max_route_factor=300.0, gps_sigma=7.0)
    assert (cfg.online.region.max_hypotheses, cfg.batch.route.max_route_factor, cfg.model.gps_sigma) == (
        16,
        300.0,
        7.0,
    )
    assert cfg == DEFAULT_CONFIG.with_settings(
        ["online.region.max_hypotheses=16", "batch.route.max_route_factor=300", "model.gps_sigma=7"]
    )
    # a whole section as a nested mapping, then bare names over it
    nested = DEFAULT_CONFIG.replace(online={"region": {"max_hops": 6}}, max_hypotheses=4)
    assert (nested.online.region.max_hops, nested.online.region.max_hypotheses) == (6, 4)
    assert DEFAULT_CONFIG.replace(batch=BATCH_CONFIG.batch).batch == BATCH_CONFIG.batch
    for bad, says in (
        ({"max_hypothesis": 8}, r"unknown parameter\(s\): max_hypothesis"),
        ({"region": {}}, r"unknown parameter\(s\): region"),
        ({"max_hypotheses": 0}, r"online\.region\.max_hypotheses must be at least 1"),
        ({"online": 3}, "online must be a OnlineConfig"),
    ):
        with pytest.raises(ConfigError, match=says):
            DEFAULT_CONFIG.replace(**bad)


def test_to_dict_is_nested_by_section() -> None:
    d = DEFAULT_CONFIG.to_dict()
    assert d["online"]["region"]["max_hypotheses"] == 32 and d["batch"]["route"]["turn_cost"] == 20.0
    assert DEFAULT_CONFIG.updated(d) == DEFAULT_CONFIG  # the dict reads back as the same config


def test_a_nested_table_changes_sections_and_names_what_is_wrong() -> None:
    cfg = BATCH_CONFIG.updated(
        {
            "model": {"gps_sigma": 6.0},
            "batch": {"route": {"max_route_factor": 300}},
            "online": {"region": {"max_hypotheses": 16}},
        }
    )
    got = (cfg.model.gps_sigma, cfg.batch.route.max_route_factor, cfg.online.region.max_hypotheses)
    assert got == (6.0, 300, 16)
    assert cfg.model.uturn_penalty == BATCH_CONFIG.model.uturn_penalty  # the rest as it was
    assert cfg.batch.split == BATCH_CONFIG.batch.split
    wide = DEFAULT_CONFIG.updated({"measurement": {"road_width": {"residential": 7.0}}})
    assert wide.measurement.road_width == (("residential", 7.0),)
    for bad, says in (
        ({"model": {"nope": 1}}, r"match\.model\.nope"),
        ({"modell": {}}, r"match\.modell: unknown section"),
        ({"model": 3}, r"match\.model: expected a table"),
        ({"online": {"region": 3}}, r"match\.online\.region: expected a table"),
        ({"online": {"regio": {}}}, r"match\.online\.regio: unknown section"),
        (
            {"batch": {"max_route_factor": 300}},
            r"match\.batch\.max_route_factor: .*did you mean match\.batch\.route\.max_route_factor\?",
        ),
        (
            {"online": {"stop": {"max_hops": 2}}},
            r"match\.online\.stop\.max_hops.*did you mean match\.online\.region\.max_hops\?",
        ),
        ({"model": {"gps_sigma": "wide"}}, r"model\.gps_sigma must be a finite non-negative number"),
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
    toml = (
        "[match.model]\ngps_sigma = 6.0\n[match.online.evidence]\nturn_window = 40\n"
        "[match.batch.route]\nmax_route_factor = 300\n"
    )
    c = _server(tmp_path, toml)
    assert (c.matcher.model.gps_sigma, c.batch_matcher.model.gps_sigma) == (6.0, 6.0)
    assert c.matcher.online.evidence.turn_window == 40 and c.batch_matcher.batch.route.max_route_factor == 300
    # each matcher keeps its own defaults where the file says nothing
    assert c.batch_matcher.model.uturn_penalty == BATCH_CONFIG.model.uturn_penalty
    assert c.matcher.model.uturn_penalty == DEFAULT_CONFIG.model.uturn_penalty
    flagged = _server(tmp_path, toml, "--set", "model.gps_sigma=7", "--set", "batch.route.max_route_factor=6")
    assert (flagged.matcher.model.gps_sigma, flagged.batch_matcher.batch.route.max_route_factor) == (7.0, 6)
    assert config_from(None, {}).matcher == DEFAULT_CONFIG
    for bad, says in (
        ("[match.model]\nnope = 1\n", "match.model.nope"),
        (
            "[match.online]\nturn_window = 40\n",
            r"match\.online\.turn_window: .*match\.online\.evidence\.turn_window",
        ),
        ("match = 3\n", "match must be a table"),
        ("matcher = 3\n", "unknown setting 'matcher'"),
    ):
        with pytest.raises(ConfigError, match=says):
            _server(tmp_path, bad)
    with pytest.raises(ConfigError, match=r"expected SECTION\.FIELD"):
        _server(tmp_path, "", "--set", "gps_sigma=7")
