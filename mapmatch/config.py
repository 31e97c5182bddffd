"""Matcher configuration: one frozen dataclass of named defaults, validated, overridable per call."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from mapmatch.errors import ConfigError


@dataclass(frozen=True)
class MatchConfig:
    """Parameters of the shared probabilistic model and of both inference modes.

    Model (shared)
    --------------
    gps_sigma : default 1-σ position error in metres when a fix gives none.
    heading_sigma : default 1-σ heading error in degrees when a fix gives a heading but no accuracy.
    heading_min_speed : m/s below which a heading is not trusted (0 disables the check).
    beta : scale in metres of |route distance - travelled distance| (Newson & Krumm's β).
    uturn_penalty : log-probability penalty of a U-turn.
    max_speed : m/s; transitions needing more are penalised.
    speed_penalty : log-probability penalty per (m/s) above ``max_speed``.

    Candidates
    ----------
    search_radius : metres around a fix to search for candidate edges.
    max_candidates : nearest roads kept per fix.

    Online
    ------
    drift_rate : expected dead-reckoning drift as a fraction of distance (thesis: 0.04).
    ambiguous_min_radius : lower bound of the ambiguous-region radius in metres.
    ambiguous_sigma_factor : the region grows to this many position σ.
    ambiguous_max_radius : upper bound of the region radius in metres.
    turn_window : odometer metres over which the heading step is measured.
    turn_threshold : degrees of heading change that count as a turn.
    reinit_time : seconds of inconsistency before re-initialising.
    reinit_distance : metres travelled while inconsistent before re-initialising.
    reinit_sigmas : a fix is inconsistent when further than this many σ from the road.
    dr_sigma_growth : fraction of distance travelled since the last GPS-aided fix added to σ.
    max_hypotheses : most path hypotheses the online filter keeps.
    turn_sigma : degrees; spread of the observed heading change around a path's predicted one.
    evidence_time : seconds of fixes that count as one independent observation (the fused
        position's error is correlated in time, so 10 Hz fixes must not count ten times).
    evidence_distance : metres travelled that count as one independent observation, when the
        distance travelled is known (a stopped vehicle's repeated fixes add no evidence).
    stop_speed : m/s; below this (from the odometer) the vehicle is stopped: its position may
        move back along the path but never on across a node (no flicker at a stop line).
    stop_hold_distance : metres; a vehicle that stops less than this past a node it went
        straight through (or has not yet turned at, by its heading) is placed before the node:
        vehicles stop at stop lines, not in junctions.
    node_hold_sigmas : a fix past the end node of the edge held is kept at that node while it
        lies within this many σ along the next edge (along-track error); further on, the
        next edge holds it.
    switch_penalty : log-probability penalty of jumping to a road the filter did not follow.
    init_commit_probability : probability at which the start-up road is committed.
    drift_decay_time : seconds over which the dead-reckoning drift σ decays once GPS is back.
    soft_reinit_sigmas : the index is searched for other roads when the fix is further than this
        many σ from the road believed.
    turn_anchor_sigma : metres; the least σ of the along-path position a turn gives (the fused
        headings aligned with the path's bearing profile); 0 disables the anchor.
    odo_scale_sigma : prior σ of the odometer's relative distance error. The turn anchor is
        carried along the path by the odometer, whose scale is learnt from anchor to anchor;
        the anchor's σ grows by the learnt scale's σ of the distance.
    bias_time : seconds; correlation time of the fix's position error, learnt across roads
        of different directions to correct the along-track position (0 disables it).
    neighbour_band : metres; roads this close to an edge at a similar bearing (parallel roads,
        fork branches) are its neighbours, tabled once per map (read when the matcher is made).
    neighbour_sigmas : the neighbours of the road believed join the filter when a GPS-aided fix
        is further than this many σ from it (0 disables it).
    return_sigmas : on the first GPS-aided fix with a heading after dead reckoning, when it is
        further than this many of its own σ from the road believed, the roads near it join the
        filter at once, weighed at its own σ (not the drift's): it is the truth, not an outlier
        (0 disables it).

    Batch
    -----
    max_route_factor : routes longer than this times the straight line (+ ``route_slack``) are cut.
    route_slack : metres added to the bound of each routing search.
    gap_time : seconds between fixes that split a track.
    gap_distance : metres between fixes that split a track.
    outlier_distance : a fix further than this from every road is unmatched.
    interpolate_distance : fixes closer than this to the previous kept fix are interpolated.
    """

    gps_sigma: float = 5.0
    heading_sigma: float = 20.0
    heading_min_speed: float = 1.0
    beta: float = 5.0
    uturn_penalty: float = 6.0
    max_speed: float = 60.0
    speed_penalty: float = 0.5

    search_radius: float = 50.0
    max_candidates: int = 8

    drift_rate: float = 0.04
    ambiguous_min_radius: float = 10.0
    ambiguous_sigma_factor: float = 2.0
    ambiguous_max_radius: float = 150.0
    turn_window: float = 30.0
    turn_threshold: float = 25.0
    reinit_time: float = 10.0
    reinit_distance: float = 100.0
    reinit_sigmas: float = 4.0
    dr_sigma_growth: float = 0.04
    max_hypotheses: int = 32
    turn_sigma: float = 20.0
    evidence_time: float = 1.0
    evidence_distance: float = 5.0
    stop_speed: float = 0.5
    node_hold_sigmas: float = 0.5
    stop_hold_distance: float = 8.0
    switch_penalty: float = 8.0
    init_commit_probability: float = 0.99
    drift_decay_time: float = 20.0
    soft_reinit_sigmas: float = 3.0
    turn_anchor_sigma: float = 1.0
    odo_scale_sigma: float = 0.02
    bias_time: float = 30.0
    neighbour_band: float = 40.0
    neighbour_sigmas: float = 0.0
    return_sigmas: float = 2.0

    max_route_factor: float = 3.0
    route_slack: float = 100.0
    gap_time: float = 120.0
    gap_distance: float = 2000.0
    outlier_distance: float = 100.0
    interpolate_distance: float = 0.0

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v < 0:
                raise ConfigError(f"{f.name} must be a finite non-negative number, got {v!r}")
        if self.max_candidates < 1:
            raise ConfigError("max_candidates must be at least 1")
        if self.max_hypotheses < 1 or self.max_hypotheses != int(self.max_hypotheses):
            raise ConfigError("max_hypotheses must be a whole number, at least 1")
        if self.init_commit_probability > 1:
            raise ConfigError("init_commit_probability must be at most 1")
        if min(self.turn_sigma, self.evidence_time, self.evidence_distance, self.drift_decay_time) <= 0:
            raise ConfigError(
                "turn_sigma, evidence_time, evidence_distance and drift_decay_time must be positive"
            )
        if self.gps_sigma <= 0 or self.beta <= 0 or self.heading_sigma <= 0:
            raise ConfigError("gps_sigma, beta and heading_sigma must be positive")

    def replace(self, **overrides: Any) -> MatchConfig:
        """A copy with some parameters changed (validated)."""
        names = {f.name for f in dataclasses.fields(self)}
        unknown = set(overrides) - names
        if unknown:
            raise ConfigError(f"unknown parameter(s): {', '.join(sorted(unknown))}")
        return dataclasses.replace(self, **overrides)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


DEFAULT_CONFIG = MatchConfig()
