"""Matcher configuration: nested, named, commented and validated defaults, overridable per call.

:class:`MatchConfig` has five sections: :class:`ModelConfig` (the probabilistic model both
inference modes share), :class:`OnlineConfig` (the per-vehicle filter), :class:`BatchConfig`
(whole-track matching), :class:`MeasurementConfig` (the online answer's map-aided
measurement) and :class:`ConfidenceConfig` (the probability the online answer reports).
``online`` and ``batch`` are made of sub-sections, one per mechanism (``online``:
``region``, ``reinit``, ``evidence``, ``bias``, ``stop``, ``anchor``, ``odometer``,
``corrections``; ``batch``: ``route``, ``track``, ``outliers``, ``split``). Every number that
changes a result is a field of one of them.

A parameter's name is its dotted path: ``config.online.region.max_hypotheses`` reads it,
``config.with_settings(["online.region.max_hypotheses=16"])`` (the CLI's ``--set``) and
``config.updated({"online": {"region": {"max_hypotheses": 16}}})`` (a TOML table) change it,
and ``config.replace(max_hypotheses=16)`` changes it by its bare name (names are unique across
all sections).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field, fields
from functools import cached_property
from typing import Any

from mapmatch.errors import ConfigError


def _full_name(name: str) -> str:
    """A field's dotted path (``online.region.max_hops``) from its bare name."""
    return ".".join(_PATHS.get(name, (name,)))


def _check_numbers(section: object) -> None:
    """Every field a finite non-negative number; whole numbers where the default is an int."""
    for f in dataclasses.fields(section):  # type: ignore[arg-type]
        v = getattr(section, f.name)
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v < 0:
            raise ConfigError(f"{_full_name(f.name)} must be a finite non-negative number, got {v!r}")
        if isinstance(f.default, int) and v != int(v):
            raise ConfigError(f"{_full_name(f.name)} must be a whole number, got {v!r}")


def _at_least(section: object, least: float, *names: str) -> None:
    """A :class:`ConfigError` naming the fields of ``names`` below ``least``."""
    low = [_full_name(n) for n in names if getattr(section, n) < least]
    if low:
        raise ConfigError(f"{', '.join(low)} must be at least {least:g}")


def _positive(section: object, *names: str) -> None:
    """A :class:`ConfigError` naming the fields of ``names`` that are zero."""
    zero = [_full_name(n) for n in names if getattr(section, n) <= 0]
    if zero:
        raise ConfigError(f"{', '.join(zero)} must be positive")


def _at_most_one(section: object, *names: str) -> None:
    """A :class:`ConfigError` naming the probabilities of ``names`` above 1."""
    high = [_full_name(n) for n in names if getattr(section, n) > 1]
    if high:
        raise ConfigError(f"{', '.join(high)} must be at most 1")


@dataclass(frozen=True)
class ModelConfig:
    """The shared probabilistic model (emission, transition) and the candidate search (``model``).

    gps_sigma : default 1-σ position error in metres when a fix gives none.
    heading_sigma : default 1-σ heading error in degrees when a fix gives a heading but no accuracy.
    heading_min_speed : m/s below which a heading is not trusted (0 disables the check).
    beta : scale in metres of |route distance - travelled distance| (Newson & Krumm's β) ...
    beta_per_m : ... plus this many metres per metre travelled: a long step's true route bends
        away from its straight line more than a short one's, so between far-apart fixes a
        route's length tells less and the fixes' distances from the roads tell more.
    uturn_penalty : log-probability penalty of a U-turn.
    max_speed : m/s; batch transitions needing more are penalised (online the odometer gives
        the travel: no speed term).
    speed_penalty : log-probability penalty per (m/s) above ``max_speed``.
    search_radius : metres around a fix to search for candidate edges.
    max_candidates : nearest roads kept per fix.
    straight_max_deg : a bearing change at most this is straight on (a straight crossing);
        one within this of a full reversal (180° less it) is a U-turn.
    """

    gps_sigma: float = 5.0
    heading_sigma: float = 20.0
    heading_min_speed: float = 1.0
    beta: float = 5.0
    beta_per_m: float = 0.0
    uturn_penalty: float = 6.0
    max_speed: float = 60.0
    speed_penalty: float = 0.5
    search_radius: float = 50.0
    max_candidates: int = 8
    straight_max_deg: float = 30.0

    def __post_init__(self) -> None:
        _check_numbers(self)
        _at_least(self, 1, "max_candidates")
        _positive(self, "gps_sigma", "beta", "heading_sigma")


@dataclass(frozen=True)
class RegionConfig:
    """The path hypotheses, the ambiguous region and when a road is committed (``online.region``).

    ambiguous_sigma_factor : the region's radius is this many position σ, at least
        ``online.bias.dr_sigma_growth`` times the map's long edge length (the dead-reckoning
        drift over one).
    ambiguous_max_radius : upper bound of the region radius in metres.
    max_hypotheses : most path hypotheses the online filter keeps.
    max_hops : most edges a path looks ahead of the vehicle's edge.
    prune_log_ratio : hypotheses this many log units below the best are dropped.
    init_max_radius : metres; the largest start-up search radius.
    commit_hold_probability : a node is not committed while the paths its commit would drop
        (another branch of a fork) still hold more than this share of the probability, until
        the best path is ``ambiguous_max_radius`` past it: leaving the ambiguous circle is no
        evidence (0 disables it).
    switch_penalty : log-probability penalty of jumping to a road the filter did not follow.
    """

    ambiguous_sigma_factor: float = 2.0
    ambiguous_max_radius: float = 150.0
    max_hypotheses: int = 32
    max_hops: int = 4
    prune_log_ratio: float = 25.0
    init_max_radius: float = 200.0
    commit_hold_probability: float = 0.05
    switch_penalty: float = 12.0

    def __post_init__(self) -> None:
        _check_numbers(self)
        _at_least(self, 1, "max_hypotheses", "max_hops")


@dataclass(frozen=True)
class ReinitConfig:
    """When the filter searches the map again: inconsistent fixes, re-initialisation, parallel
    roads and the return of GPS (``online.reinit``).

    soft_reinit_sigmas : the index is searched for other roads when the fix is further than this
        many σ from the road believed ...
    against_heading_deg : ... or the fix heads against that road by more than this (and no
        hypothesis starts, or joins, against the fix's heading by more); at most
        once per ``online.evidence.evidence_time`` (one independent observation).
    reinit_sigmas : a fix is inconsistent when further than this many σ from the road.
    reinit_time : seconds of inconsistency before re-initialising.
    reinit_distance : metres travelled while inconsistent before re-initialising.
    far_off : metres; a fix further than this from the map's bounds is not placed.
    return_sigmas : on the first GPS-aided fix with a heading after dead reckoning (and, at most
        every ``online.evidence.evidence_time``, on those after it while the drift σ blends out), when it is
        further than this many of its own σ from the road believed, the roads near it join the
        filter at once, weighed at its own σ (not the drift's): it is the truth, not an outlier
        (0 disables it).
    """

    soft_reinit_sigmas: float = 3.0
    against_heading_deg: float = 100.0
    reinit_sigmas: float = 4.0
    reinit_time: float = 10.0
    reinit_distance: float = 100.0
    far_off: float = 100_000.0
    return_sigmas: float = 2.0

    def __post_init__(self) -> None:
        _check_numbers(self)


@dataclass(frozen=True)
class EvidenceConfig:
    """What a fix weighs: the turn seen, its evidence weight and its least σ (``online.evidence``).

    turn_window : odometer metres over which the heading step is measured.
    (A heading sample is kept every ``online.corrections.trail_step`` odometer metres.)
    turn_max_samples : heading samples kept at most (a memory bound per vehicle).
    turn_sigma : degrees; spread of the observed heading change around a path's predicted one.
    evidence_time : seconds of fixes that count as one independent observation (the fused
        position's error is correlated in time, so 10 Hz fixes must not count ten times).
    evidence_distance : metres travelled that count as one independent observation, when the
        distance travelled is known; a fix adds its time over ``bias.bias_time`` (the fix
        error's correlation time) to that share, so a standing vehicle's fixes add evidence
        slowly: not never (a start-up between two roads would be decided by its first fix),
        and not once per fix.
    stopped_heading_weight : a stopped vehicle's fused heading (a fix with ``model.heading_sigma``,
        gyro-aided, which holds at a standstill where a GPS course does not) scores the paths
        with this share of the fix's time weight, the share its distance weight leaves out: a
        vehicle turning round while stopped at a node shows which road it faces (0 disables it).
    pos_sigma_floor : metres; the least position σ of a fix (reported ones are optimistic).
    heading_sigma_floor_deg : the least heading σ of a fix, GPS-aided or dead-reckoned.
    """

    turn_window: float = 30.0
    turn_max_samples: int = 48
    turn_sigma: float = 20.0
    evidence_time: float = 1.0
    evidence_distance: float = 5.0
    stopped_heading_weight: float = 1.0
    pos_sigma_floor: float = 2.0
    heading_sigma_floor_deg: float = 10.0

    def __post_init__(self) -> None:
        _check_numbers(self)
        _positive(self, "turn_sigma", "evidence_time", "evidence_distance")


@dataclass(frozen=True)
class BiasConfig:
    """The fix's error: dead-reckoning drift, the learnt fix bias and residuals, and the
    along-track correction (``online.bias``).

    dr_sigma_growth : fraction of distance travelled since the last GPS-aided fix added to σ.
    drift_decay_time : seconds over which the dead-reckoning drift σ decays once GPS is back.
        A fusion filter whose covariance grew in the outage takes most of the first fix, so
        the decay is short: a long one leaves the matcher trusting the dead-reckoned road long
        after GPS is back.
    bias_time : seconds; correlation time of the fix's position error, learnt across roads
        of different directions to correct the along-track position (0 disables it); a fix
        also adds its time over this to its evidence weight (``online.evidence``).
    bias_white_fraction : the share of the fix's σ that is white (not learnt as bias).
    bias_emission : share of the learnt fix bias's part across the road taken off a GPS-aided
        fix's distance from each road when the paths are weighed: the receiver's error lasts
        minutes, so a fix that has lain 10 m left of the road is no evidence for the road
        10 m to the left (0 disables it). Half: the learnt bias is an estimate, and taking all
        of it off lets a single fix flip the road believed.
    residual_time : seconds over which the road residuals (position, heading) are averaged.
    learned_pos_sigma_max : metres; most position σ the residuals may teach.
    learned_heading_sigma_max_deg : most heading σ the residuals may teach.
    With GPS, the step from a hypothesis's place (where the along-track correction put it: the
    fix's projection less the learnt fix bias along the road, fused with the turn anchor) to a
    candidate point is judged to the point's place corrected alike (not to its uncorrected
    projection, which would count the offset between a projection and its corrected place
    against every step, ten times a second at 10 Hz). A place the path's turn stops short of
    its estimate pays by the correction's miss, and its step is judged to the estimate.
    """

    dr_sigma_growth: float = 0.04
    drift_decay_time: float = 4.0
    bias_time: float = 30.0
    bias_white_fraction: float = 0.5
    bias_emission: float = 0.5
    residual_time: float = 20.0
    learned_pos_sigma_max: float = 10.0
    learned_heading_sigma_max_deg: float = 30.0

    def __post_init__(self) -> None:
        _check_numbers(self)
        _positive(self, "drift_decay_time", "residual_time", "bias_white_fraction")


@dataclass(frozen=True)
class StopConfig:
    """Stops, nodes, and the rules that hold at any fix rate (``online.stop``).

    stop_speed : m/s; below this (from the odometer) the vehicle is stopped: its position may
        move back along the path but its fixes never move it on across a node (no flicker at
        a stop line); the odometer's distance does, while the fixes keep within the region
        radius of the road (a vehicle creeping past a node, or carried without GPS).
    stop_time : seconds; the speed compared with ``stop_speed`` is the odometer's averaged over
        this long (exponentially), whatever the fix rate: over 0.1 s an odometer's noise of a
        few centimetres reads as walking pace, and a parked vehicle at 10 Hz kept moving on.
    zero_speed : m/s; below this odometer speed (averaged over ``stop_time``) the vehicle
        stands and the fix's distance counts as zero (a zero-velocity update): a speed sensor's
        noise at a standstill is never negative, so at 10 Hz its sum crept a parked vehicle
        forward by metres a minute, carrying the along-track anchor ahead of it (0 disables it).
    still_distance : metres; moving less than this between fixes, the vehicle stands.
    node_hold_sigmas : a vehicle past a node goes back across it only when the fix lies more
        than this many σ before it (no flicker at a crossing).
    """

    stop_speed: float = 0.5
    stop_time: float = 1.0
    zero_speed: float = 0.2
    still_distance: float = 0.05
    node_hold_sigmas: float = 0.5

    def __post_init__(self) -> None:
        _check_numbers(self)
        _positive(self, "stop_time")


@dataclass(frozen=True)
class AnchorConfig:
    """The turn anchor: the along-path position a turn gives (``online.anchor``).

    turn_anchor_sigma : metres; the least σ of the along-path position a turn gives (the fused
        headings aligned with the path's bearing profile); 0 disables the anchor.
    align_search_max : metres; a turn's heading profile is searched within
        ``online.reinit.soft_reinit_sigmas`` fix σ of the position believed (as far as a fix on
        the road may lie from it), up to this many metres.
    align_heading_sigma_min_deg : the least heading σ the alignment assumes.
    align_rms_max_deg : a worse fit: the path is not what the vehicle drove, no anchor.
    align_cover : metres; the heading samples must reach this far either side of the node.
    """

    turn_anchor_sigma: float = 1.0
    align_search_max: float = 40.0
    align_heading_sigma_min_deg: float = 3.0
    align_rms_max_deg: float = 20.0
    align_cover: float = 3.0

    def __post_init__(self) -> None:
        _check_numbers(self)


@dataclass(frozen=True)
class OdometerConfig:
    """The odometer's scale, learnt from turn anchors and from the GPS (``online.odometer``).

    odo_scale_sigma : prior σ of the odometer's relative distance error. The scale is a
        running estimate per session (a Kalman filter with this prior): from the GPS, the
        path metres between the projections of the GPS-aided fixes onto the path driven
        against the odometer's (the fix's error along the road modelled as the learnt fix
        bias is: ``bias.bias_time``, ``bias_white_fraction``); and from anchor to anchor.
        The turn anchor is carried along the path by the odometer; its σ grows by the learnt
        scale's σ of the distance. 0 learns no scale.
    odo_scale_floor : relative odometer error left after learning its scale.
    odo_scale_max : the largest relative scale error learnt.
    scale_min_distance : metres; turn anchors closer than this teach nothing about the scale ...
    scale_max_distance : ... and further apart the path between them is more likely wrong.
    scale_path_error : relative error of a path's length between turn anchors.
    """

    odo_scale_sigma: float = 0.02
    odo_scale_floor: float = 0.002
    odo_scale_max: float = 0.2
    scale_min_distance: float = 20.0
    scale_max_distance: float = 600.0
    scale_path_error: float = 0.005

    def __post_init__(self) -> None:
        _check_numbers(self)


@dataclass(frozen=True)
class CorrectionsConfig:
    """The corrections of an ambiguous region, re-timed crossings and the report (``online.corrections``).

    max_live : most fixes of an ambiguous region remembered for corrections (every fix until
        then).
    trail_step : metres; the odometer trail for re-timing crossings keeps a point this often ...
    trail_max : ... at most this many points ...
    trail_max_distance : ... and crossings at most this many metres back.
    max_path_edges : most edges an imported session may hold in one path list (a hypothesis's
        path, the edges since the last turn anchor): with ``online.region.max_hypotheses``,
        ``model.max_candidates``, ``max_live``, ``online.evidence.turn_max_samples`` and
        ``trail_max`` it bounds the
        work one imported session can cost (the matcher's own paths hold a few dozen edges).
    revise_sigmas : a revised crossing moves only as far as its anchor is this many σ sure.
    report_back_ratio : reporting an edge behind the one reported needs this much more mass.
    """

    max_live: int = 48
    trail_step: float = 2.0
    trail_max: int = 150
    trail_max_distance: float = 300.0
    max_path_edges: int = 1024
    revise_sigmas: float = 1.0
    report_back_ratio: float = 3.0

    def __post_init__(self) -> None:
        _check_numbers(self)
        _at_least(self, 1, "max_live")
        _at_least(self, 2, "trail_max", "max_path_edges")
        _positive(self, "trail_step")


@dataclass(frozen=True)
class OnlineConfig:
    """The online filter (:mod:`mapmatch.online`): one sub-section per mechanism.

    region : the path hypotheses, the ambiguous region and when a road is committed
        (:mod:`mapmatch.online.region`, :mod:`mapmatch.online.hypotheses`).
    reinit : when the filter searches the map again: inconsistent fixes, re-initialisation,
        parallel roads and the return of GPS (:mod:`mapmatch.online.matcher`).
    evidence : what a fix weighs: the turn seen, the evidence weight of a fix, the σ floors
        (:mod:`mapmatch.online.step`, :mod:`mapmatch.online.placement`).
    bias : the fix's error: dead-reckoning drift, the learnt bias and residuals, the
        along-track correction (:mod:`mapmatch.online.bias`).
    stop : stops, nodes and the fix rate (the placement and the transition).
    anchor : the turn anchor (:mod:`mapmatch.online.anchor`).
    odometer : the odometer's learnt scale (:mod:`mapmatch.online.anchor`).
    corrections : the corrections of an ambiguous region, re-timed crossings and the report
        (:mod:`mapmatch.online.correction`, :mod:`mapmatch.online.report`).
    """

    region: RegionConfig = field(default_factory=RegionConfig)
    reinit: ReinitConfig = field(default_factory=ReinitConfig)
    evidence: EvidenceConfig = field(default_factory=EvidenceConfig)
    bias: BiasConfig = field(default_factory=BiasConfig)
    stop: StopConfig = field(default_factory=StopConfig)
    anchor: AnchorConfig = field(default_factory=AnchorConfig)
    odometer: OdometerConfig = field(default_factory=OdometerConfig)
    corrections: CorrectionsConfig = field(default_factory=CorrectionsConfig)

    def __post_init__(self) -> None:
        _check_sections(self)


@dataclass(frozen=True)
class RouteConfig:
    """The route between two fixes: its search bounds and its costs (``batch.route``).

    max_route_factor : routes longer than this times the straight line (+ ``route_slack``) are cut.
    route_slack : metres added to the bound of each routing search (and ``turn_cost``: the
        search counts turn costs as metres).
    route_speed : m/s; a route may also be as long as this speed allows over the time between
        its two fixes: where fixes are far apart in time the road may go far round (a dual
        carriageway's turning point, a one-way loop, a logger gap). It matters most for sparse
        tracks. A fix the route can reach is visited: 30 s apart, a fix beside a side road
        becomes a trip up it (with 0 the bound is the distance's alone and it is left out).
    beta_per_s : metres added to the model's β per second of the step's driving time: the
        time between its two fixes over the number of the track's fix intervals between them
        (a stop, whose fixes are interpolated, is not driving). The longer a vehicle drives
        between two fixes, the further round it may have gone, whatever the straight line.
    turn_cost : metres a route pays for turning back at a node (a U-turn at a dead end); a
        turn by θ pays ``(1 - cos θ) / 2`` of it, a right angle half. Between two fixes the
        route with fewer and gentler turns wins over one of about the same length, as drivers
        do; too high a cost makes dense tracks' routes avoid the turns they took. A route's
        turn costs count as metres wherever its length is used (the transition, the search
        bound, the speed checks). A route table (:class:`~mapmatch.route_table.Ubodt`) holds one turn cost; a
        matcher uses it only for configs with that turn cost.
    route_lp_cut : routes are searched only as a fallback beyond the travelled distance plus
        this many β (the base ``model.beta``, without ``model.beta_per_m``'s growth): a wider
        first search costs time on dense maps, and between sparse fixes it may find a better
        route than the first one within the cut.
    reverse_tolerance : metres a candidate may fall behind the previous one on the same edge and
        count as standing. On a one-way edge, which no vehicle drives backwards, a candidate up
        to ``model.search_radius`` behind counts as standing (noise about the place the vehicle
        stands at, the fixes' distance apart charged by the transition), not as a fix to leave
        out at the cost of the place the route reached.
    stop_uturn_penalty : a step slower on average than ``model.heading_min_speed`` (the speed
        below which a vehicle's heading tells nothing: as good as stopped) over at least
        ``batch.outliers.spike_max_time`` seconds (the time a car needs to turn round) spans a
        stop, across which turning round at a junction costs this U-turn penalty (turning round
        there, e.g. in a yard off the mapped road, is common; mid-road U-turns keep the full
        penalty). 0.5 keeps a small preference for driving on; much more and a car that stops
        in a turning loop and turns back at its junction is matched round the loop.
    """

    max_route_factor: float = 3.0
    route_slack: float = 100.0
    route_speed: float = 25.0
    beta_per_s: float = 0.5
    turn_cost: float = 20.0
    route_lp_cut: float = 30.0
    reverse_tolerance: float = 10.0
    stop_uturn_penalty: float = 0.5

    def __post_init__(self) -> None:
        _check_numbers(self)


@dataclass(frozen=True)
class TrackConfig:
    """The track's own σ, thinning, the fixes' σ floors and the direction of travel (``batch.track``).

    track_sigma_max : metres; a track's fixes without their own accuracy take the larger of
        ``model.gps_sigma`` and the track's own σ, up to this: 1.4826 times the median distance of its
        fixes to their nearest road (Newson and Krumm's robust estimate: a worse receiver
        shows in how far its fixes lie from the roads). 0: always ``model.gps_sigma``. The σ counts
        in the emissions, the off-map limit and the jump rule.
    track_sigma_min_fixes : a track with fewer fixes near a road than this keeps
        ``model.gps_sigma``: a median of a few distances is no estimate of a receiver (four
        fixes 10 m off their roads would give σ 15 m and thin out the fixes between the first
        and last, the evidence of which road the first lies on).
    thin_sigmas : a track whose own σ exceeds ``model.gps_sigma`` is thinned (as by
        fixes closer than ``model.gps_sigma``) at this many times the excess: a worse receiver's fixes
        close together share their error, so they are less evidence than their number says
        (0: never; ``bench/bench_batch_robust.py --sets noise`` adds error to real tracks to
        judge it).
    track_pos_sigma_floor : metres; the least position σ of a fix's own accuracy (a reported σ near
        zero would make one fix outweigh the whole track).
    track_heading_sigma_floor_deg : the least heading σ (degrees) of a fix's own heading or of
        the direction of travel.
        Where a fix has no heading, the direction of travel from its neighbours (both legs at
        least ``model.gps_sigma`` metres, turning by at most ``model.straight_max_deg``) is its
        heading against the road's bearing and one-way direction, with a σ of
        ``model.straight_max_deg`` (legs that may turn by that much tell the direction no
        better; 0 disables it). One σ is short: consecutive fixes share most of their error,
        so even a slow vehicle's legs of a few metres tell its direction.
    motion_end_leg_max : metres; the track's first and last fix take the direction of travel
        of their neighbour's two legs only where their own leg is at most this long (0: any
        length). A turn at a junction soon after the first fix, or soon before the last, leaves
        both legs straight: over a long leg it goes unseen, and the direction it gives would put
        the fix on the road turned onto, across the corner. At 1 Hz (legs of up to 30 m) the
        end fixes keep it; at one fix every 10 or 30 s they do not.
    """

    track_sigma_max: float = 30.0
    track_sigma_min_fixes: int = 10
    thin_sigmas: float = 6.0
    track_pos_sigma_floor: float = 0.5
    track_heading_sigma_floor_deg: float = 1.0
    motion_end_leg_max: float = 50.0

    def __post_init__(self) -> None:
        _check_numbers(self)


@dataclass(frozen=True)
class OutliersConfig:
    """Fixes off the map, jumps, and the fixes left out as outliers (``batch.outliers``).

    outlier_distance : a fix further than this from every road is unmatched.
    off_map_sigmas : a fix further than this many σ from every road is off the map: unmatched,
        never routed to a far road (``outlier_distance`` caps it). Leaving a fix out as an
        outlier, where that competes with visiting it (``outlier_lookahead``), costs the
        emission of a fix at this limit, ½ ``off_map_sigmas``² in log-probability (12.5 at
        5 σ): another choice is taken only if it wins by more.
    emission_prune : candidates whose emission log-probability is this far below their fix's
        best are dropped.
    spike_speed : m/s; the fastest a car turns round or leaves the mapped road (a run of fixes
        off the map faster than this is GPS trouble on a road: ``batch.split.off_map_cut_fixes``).
        A fix the track reaches and leaves in opposite directions, both legs
        longer than ``off_map_sigmas`` σ (beyond the fixes' noise by the off-map limit), is
        dropped as a jump when visiting it needs more than this mean speed between its
        neighbours (turning round needs slowing down; 0 disables).
    spike_max_time : seconds; a jump may also be a run of fixes lasting up to this (a
        multipath burst): such a run, reached and left in opposite directions, is dropped as
        one when visiting it needs more than ``spike_speed`` (the shortest such run; 0: single
        fixes only). Short, as a car cannot turn round at that speed within a few seconds. The
        same time, the least a car needs to turn round, makes a slow step a stop
        (``batch.route.stop_uturn_penalty``).
    max_skip : fixes in a row that may be left out as unreachable outliers before the track is
        split ...
    max_skip_time : ... and only once they reach this many seconds after the last fix kept
        (0: the count alone; past ``max_skip`` fixes, those kept before them are first tried
        as the outliers, a drift onto a road that leads nowhere). A run of fixes judged by
        its count alone would split a dense track where the same drive sampled sparsely is
        bridged: the time a vehicle spends off the route's roads is what the fixes tell,
        whatever their rate. Tracks without times are judged by the count.
    outlier_lookahead : 1: where a fix cannot be reached from the previous kept fix, also try
        leaving out that previous fix instead, and keep whichever choice reaches the next fix
        with the higher score (a stray fix on a side road is dropped, not the good one after
        it; where the previous fix starts its piece, the fix starts it instead: a first fix in
        a car park by some other road); and where a fix is reached only after leaving out two
        or more before it, also try leaving out the fix before them instead (a stray fix
        followed by another, or by a road that does not lead on); and where the two steps
        through a fix cost more than ``leave_out_cost``, also try the step past it (a stray fix
        the route bent to); and leave out the track's first or last fix where visiting it
        costs more than ``leave_out_cost``: its emission against a fix on its road plus the
        detour of its step, in β (a last fix in a car park by some road, minutes after the
        drive; not at a split, where the fixes are already in doubt), then the next one the
        same way (the new first fix's candidate chosen again, as if the track began there),
        and so is a piece of one fix at the track's start or end beside another piece (one
        fix makes no route: a fix by some road before or after a run off the route); 0:
        always leave out the unreachable fix, visit every reachable one. Each fix left out
        costs ½ ``off_map_sigmas``² (:attr:`leave_out_cost`). A step whose route is longer
        than the distance travelled between its fixes by more than twice that many of its β
        (``off_map_sigmas``²: the detour costs more than both its fixes left out) is
        impossible, whatever the time allows: the fix is left out as an outlier, or the match
        splits there. A fix beside some road where the map ends (a car park, an unmapped lane)
        is then not joined to the route by a long way round; the limit (25 β at 5 σ) lies
        above the detours true routes take (``bench/bench_batch_ends.py`` removes the roads at
        a true route's ends to see how much road a match adds there).
    """

    outlier_distance: float = 100.0
    off_map_sigmas: float = 5.0
    emission_prune: float = 12.5
    spike_speed: float = 20.0
    spike_max_time: float = 5.0
    max_skip: int = 8
    max_skip_time: float = 60.0
    outlier_lookahead: int = 1

    def __post_init__(self) -> None:
        _check_numbers(self)
        _positive(self, "off_map_sigmas")
        if self.outlier_lookahead not in (0, 1):
            raise ConfigError(f"{_full_name('outlier_lookahead')} must be 0 or 1")

    @property
    def leave_out_cost(self) -> float:
        """Log-probability each fix left out costs where leaving out competes with visiting: the
        emission of a fix at the off-map limit, ½ ``off_map_sigmas``²."""
        return 0.5 * self.off_map_sigmas**2

    @property
    def detour_cost_max(self) -> float:
        """β of detour beyond which a step is impossible: twice :attr:`leave_out_cost`,
        ``off_map_sigmas``² (the detour costs more than leaving out both its fixes)."""
        return 2.0 * self.leave_out_cost


@dataclass(frozen=True)
class SplitConfig:
    """Where a track is split into pieces or its route cut (``batch.split``).

    split_speed : m/s; a car's top speed. A step whose route is longer than the straight line
        between its fixes by more than this times its time (plus the fixes' noise: twice
        ``batch.outliers.off_map_sigmas`` σ, each of the two fixes up to the off-map limit
        from its road) is impossible: the fix is left out as an outlier, or the match splits
        there. Where the fixes themselves move no faster than this, a route needing more
        than this average speed over the step's time (plus the same noise) is impossible
        too: sparse fixes either side of a road the map lacks are then not joined round by a
        far longer way. Where the fixes move faster, their timestamps are in doubt, and only the detour
        is judged (0 disables both checks). A step faster than this and longer than it takes
        over ``batch.outliers.max_skip_time`` (3 km at the defaults: further than the car can
        go while its fixes are left out as outliers) is a jump (two drives joined, a clock
        error) and splits the track; a slower one was driven (a logger off, a sparse track) and
        its route is searched as any step's (with either 0, distance never splits).
    off_map_cut : metres; a run of fixes the route leaves out (off the map, or on roads the
        route cannot reach in time: unreachable outliers) travelling at least this far among
        themselves (the track leaves the route's roads and comes back) cuts the route there,
        at the run's first fix, and is not routed round (0: never cut) ...
    off_map_cut_fixes : ... if the run has at least this many fixes, and is no faster from
        its first fix to its last than ``batch.outliers.spike_speed`` (the speed a car turns
        round or leaves the mapped road at, no faster; 0: any speed, and the duration rule
        below takes any duration). Cars leave the mapped roads slowly (car parks, lanes,
        yards); two or three fixes left out at speed are a fast road's interchange or ramp
        with GPS trouble, or a multipath burst, where the route is the better guess. A run
        also cuts where it lasts as long as ``off_map_cut`` takes at that speed (10 s at the
        defaults) and,
        with its legs from the route's fix before it and back to the one after it, travels
        ``off_map_cut``: sparse fixes in a yard off the map travel little among themselves
        (three fixes 20 s apart, 70 m) while the time allows a way round; a car parked beside
        the road, its fixes drifting off the map, is not cut (short legs).
        A run ``off_map_cut`` does not cut (a fast one: GPS trouble on a road, where the route
        is the better guess) is bridged only by a route at most twice ``off_map_cut`` longer
        than the path through its fixes, from the fix before it to the one after (with
        ``off_map_cut`` 0: any route). Its fixes still tell where the car went: a route
        kilometres round, where the map lacks the road they follow, is not it; the step then
        fails, as a step no route reaches, and the route is cut there. Twice: fixes that far
        off a road on both sides of the run; a smaller slack would also cut where a track's
        fixes lie far off its true route. Only runs of at least ``off_map_cut_fixes`` fixes
        are held to it: one or two sparse fixes do not trace a winding road.
    """

    split_speed: float = 50.0
    off_map_cut: float = 200.0
    off_map_cut_fixes: int = 3

    def __post_init__(self) -> None:
        _check_numbers(self)

    @property
    def bridge_slack(self) -> float:
        """Metres a route bridging a run of fixes off the map may be longer than the path
        through its fixes: twice ``off_map_cut`` (0: any route)."""
        return 2.0 * self.off_map_cut


@dataclass(frozen=True)
class BatchConfig:
    """Whole-track matching (:mod:`mapmatch.batch`): one sub-section per concern.

    route : the route between two fixes: its search bounds and its costs.
    track : the track's own σ, thinning, the fixes' σ floors and the direction of travel.
    outliers : fixes off the map, jumps and the fixes left out as outliers.
    split : where a track is split into pieces or its route cut.
    """

    route: RouteConfig = field(default_factory=RouteConfig)
    track: TrackConfig = field(default_factory=TrackConfig)
    outliers: OutliersConfig = field(default_factory=OutliersConfig)
    split: SplitConfig = field(default_factory=SplitConfig)

    def __post_init__(self) -> None:
        _check_sections(self)


# default carriageway width in metres per OSM highway class (all lanes, both directions on a
# two-way road; one carriageway of a dual road drawn as one-way); unknown classes: 6 m
ROAD_WIDTH_M: tuple[tuple[str, float], ...] = (
    ("motorway", 7.5),
    ("trunk", 7.5),
    ("primary", 7.0),
    ("secondary", 6.5),
    ("tertiary", 6.0),
    ("unclassified", 5.0),
    ("residential", 5.5),
    ("living_street", 4.5),
    ("service", 3.5),
    ("track", 3.0),
    ("motorway_link", 4.0),
    ("trunk_link", 4.0),
    ("primary_link", 4.0),
    ("secondary_link", 4.0),
    ("tertiary_link", 4.0),
)


@dataclass(frozen=True)
class MeasurementConfig:
    """How the map-aided measurement is built and when it is usable (``measurement``).

    min_probability : the reported road's probability below which the measurement is not usable.
    settle_distance : metres driven after a (re)initialisation before the measurement is usable.
    map_sigma : metres; 1-σ error of the map's centre line.
    lane_width : metres per lane, for a road with a ``lanes`` tag but no ``width``.
    default_width : metres; the road width for a class not in ``road_width``.
    road_width : (class, metres) default carriageway width per OSM highway class.
    road_heading_sigma : degrees; least σ of the road heading (lane changes, drawing).
    node_heading_sigma : degrees added when one along-track σ reaches past the edge's end.
    along_sigma_max : metres; the along-track σ is capped here (a very uncertain position is
        as good as none, and keeps the covariance finite).
    straddle : metres; a vehicle this far past a node is on both roads (half a car length):
        the road's probability counts the along-track position's share on the edge widened
        by this at each end.
    """

    min_probability: float = 0.99
    settle_distance: float = 100.0
    map_sigma: float = 1.0
    lane_width: float = 3.25
    default_width: float = 6.0
    road_width: tuple[tuple[str, float], ...] = ROAD_WIDTH_M
    road_heading_sigma: float = 2.0
    node_heading_sigma: float = 5.0
    along_sigma_max: float = 1000.0
    straddle: float = 2.5

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "road_width":
                if not all(isinstance(c, str) and math.isfinite(w) and w > 0 for c, w in v):
                    raise ConfigError(f"{_full_name('road_width')} must be (class, positive metres) pairs")
                continue
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v < 0:
                raise ConfigError(f"{_full_name(f.name)} must be a finite non-negative number, got {v!r}")
        _at_most_one(self, "min_probability")
        _positive(self, "map_sigma", "lane_width", "default_width", "road_heading_sigma")

    @cached_property
    def width_of(self) -> dict[str, float]:
        """``road_width`` as a mapping."""
        return dict(self.road_width)

    @cached_property
    def cross_sigmas(self) -> dict[tuple[str, bool], float]:
        """:func:`cross_track_sigma` of a road without width tags by (class, one-way), as
        computed so far."""
        return {}


@dataclass(frozen=True)
class ConfidenceConfig:
    """The probability an online answer reports: a logistic model of the answer being on the
    right road (``confidence``), estimated on real drives (``bench/bench_online_real.py
    --calibration``; the out-of-fold figures are in the calibration benchmark).

    The model's log-odds are ``coef_intercept`` + ``coef_log_odds`` times the log-odds of the
    road's probability (the filter's mass of the path, times the along-track position's share
    on the edge where that applies) + ``coef_heading`` per 10° between the fix's heading and
    the road's (at most ``heading_cap``) + when another road runs alongside, ``coef_parallel``
    plus ``coef_parallel_gap`` per σ (the fix's) by which that road is nearer to the fix than
    the answer's, counted from ``gap_cap`` further (0) to ``gap_cap`` nearer. Coefficients 0,
    1, 0, 0, 0 report the road's probability itself.

    coef_intercept, coef_log_odds, coef_heading, coef_parallel, coef_parallel_gap : the
        model's coefficients (any sign).
    parallel_radius : metres; a road within this of the answer's stretch of its edge, not
        sharing the edge's nodes there (a road whose nearest point lies within
        ``measurement.map_sigma`` of a shared node leaves at the junction), at a bearing
        within ``model.straight_max_deg`` of the edge's, runs alongside it.
    parallel_spacing : metres; the length of the stretches an edge is looked at in.
    probability_floor : the road's probability is taken in [floor, 1 - floor] for its log-odds.
    heading_cap : degrees; a fix further off the road's bearing says no more.
    gap_cap : fix σ; a road alongside nearer or further than the answer's by more says no more.
    """

    coef_intercept: float = 4.025
    coef_log_odds: float = 0.198
    coef_heading: float = -0.543
    coef_parallel: float = -1.167
    coef_parallel_gap: float = -0.351
    parallel_radius: float = 40.0
    parallel_spacing: float = 20.0
    probability_floor: float = 1e-6
    heading_cap: float = 90.0
    gap_cap: float = 5.0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise ConfigError(f"{_full_name(f.name)} must be a finite number, got {v!r}")
            if not f.name.startswith("coef_") and v <= 0:
                raise ConfigError(f"{_full_name(f.name)} must be positive")
        if self.probability_floor >= 0.5:
            raise ConfigError(f"{_full_name('probability_floor')} must be below 0.5")


def _sub_sections(cls: type) -> dict[str, type]:
    """The sub-sections of a section class by name (empty for a section of plain fields)."""
    out: dict[str, type] = {}
    for f in dataclasses.fields(cls):
        factory = f.default_factory
        if isinstance(factory, type) and dataclasses.is_dataclass(factory):
            out[f.name] = factory
    return out


def _check_sections(section: object) -> None:
    """Each sub-section of ``section`` an instance of its class."""
    for name, cls in _sub_sections(type(section)).items():
        if not isinstance(getattr(section, name), cls):
            raise ConfigError(f"{_SECTION_PATH.get(type(section), '')}{name} must be a {cls.__name__}")


def _walk(cls: type, path: tuple[str, ...]) -> Iterator[tuple[type, tuple[str, ...], bool]]:
    """Every section class under ``cls`` (itself first) with its path, and whether it is a leaf."""
    subs = _sub_sections(cls)
    yield cls, path, not subs
    for name, sub in subs.items():
        yield from _walk(sub, (*path, name))


def _leaf_paths() -> dict[str, tuple[str, ...]]:
    """Every field's dotted path by its bare name; a name used twice is an error."""
    out: dict[str, tuple[str, ...]] = {}
    for cls, path, leaf in _walk(MatchConfig, ()):
        for f in dataclasses.fields(cls) if leaf else ():
            if f.name in out:
                raise ConfigError(f"{f.name} is a field of two sections")  # keeps bare names unique
            out[f.name] = (*path, f.name)
    return out


@dataclass(frozen=True)
class MatchConfig:
    """Parameters of the shared model, of both inference modes and of the map-aided
    measurement, in four sections (``online`` and ``batch`` of sub-sections). A parameter's full
    name is its dotted path (``model.gps_sigma``, ``online.region.max_hypotheses``); field names
    are unique across all sections, so :meth:`replace` also takes them bare."""

    model: ModelConfig = field(default_factory=ModelConfig)
    online: OnlineConfig = field(default_factory=OnlineConfig)
    batch: BatchConfig = field(default_factory=BatchConfig)
    measurement: MeasurementConfig = field(default_factory=MeasurementConfig)
    confidence: ConfidenceConfig = field(default_factory=ConfidenceConfig)

    def __post_init__(self) -> None:
        _check_sections(self)

    def replace(self, **overrides: Any) -> MatchConfig:
        """A copy with some parameters changed (validated): by bare field name, or a whole
        top-level section (a section instance or a nested mapping of its fields)."""
        sections = _sub_sections(MatchConfig)
        unknown = sorted(set(overrides) - set(_PATHS) - set(sections))
        if unknown:
            raise ConfigError(f"unknown parameter(s): {', '.join(unknown)}")
        whole = {k: v for k, v in overrides.items() if k in sections and not isinstance(v, Mapping)}
        cfg = dataclasses.replace(self, **whole)
        nested: dict[str, Any] = {
            k: v for k, v in overrides.items() if isinstance(v, Mapping) and k in sections
        }
        cfg = cfg.updated(nested) if nested else cfg
        flat: dict[str, Any] = {}
        for name, value in overrides.items():
            if name in _PATHS:
                _put(flat, _PATHS[name], value)
        return cfg.updated(flat) if flat else cfg

    def with_settings(self, settings: Sequence[str]) -> MatchConfig:
        """A copy with ``SECTION.FIELD=VALUE`` settings (numbers; ``online.region.max_hops=6``)
        applied; a setting without ``=``, of an unknown name or with a value that is no number
        is a :class:`ConfigError` naming it (a bare or misplaced field name with its full
        name)."""
        nested: dict[str, Any] = {}
        for kv in settings:
            name, sep, value = kv.partition("=")
            name = name.strip()
            if not sep:
                raise ConfigError(f"{kv!r}: expected SECTION.FIELD=VALUE (for example model.gps_sigma=8)")
            path = tuple(name.split("."))
            if len(path) < 2:
                raise ConfigError(f"{name!r}: expected SECTION.FIELD{_hint(name)}")
            try:  # "8" an integer (counts), "0.5" or "1e3" a float
                number = int(value) if value.strip().lstrip("+-").isdigit() else float(value)
            except ValueError:
                raise ConfigError(f"{name}: {value!r} is not a number") from None
            _put(nested, path, number)
        return self.updated(nested)

    def updated(self, nested: Mapping[str, Any], *, prefix: str = "") -> MatchConfig:
        """A copy with the values of ``nested`` (``{section: {sub-section: {field: value}}}``,
        as a TOML table gives them) applied and validated; an unknown section or field is a
        :class:`ConfigError` naming its dotted path with ``prefix`` (``match.`` in the server's
        file)."""
        return _updated(self, nested, (), prefix)

    def to_dict(self) -> dict[str, Any]:
        """Nested plain values, one mapping per section and sub-section."""
        return dataclasses.asdict(self)


def _put(nested: dict[str, Any], path: tuple[str, ...], value: Any) -> None:
    """Set ``value`` at ``path`` in a nested mapping."""
    for part in path[:-1]:
        nested = nested.setdefault(part, {})
        if not isinstance(nested, dict):
            raise ConfigError(f"{'.'.join(path)}: {part} is a field, not a section")
    nested[path[-1]] = value


def _hint(name: str, prefix: str = "") -> str:
    """``; did you mean SECTION.FIELD?`` for a known field's bare name or a near miss of one
    (``max_hypothesis``), else nothing."""
    near = [name] if name in _PATHS else difflib.get_close_matches(name, _PATHS, n=1, cutoff=0.85)
    return f"; did you mean {prefix}{'.'.join(_PATHS[near[0]])}?" if near else ""


def _updated(section: Any, changes: Any, path: tuple[str, ...], prefix: str) -> Any:
    """``section`` (at ``path``) with the nested ``changes`` applied, validated."""
    where = prefix + ".".join(path)
    if not isinstance(changes, Mapping):
        raise ConfigError(f"{where}: expected a table of its fields")
    subs = _sub_sections(type(section))
    names = {f.name for f in dataclasses.fields(section)}
    unknown = [k for k in changes if k not in names]
    if unknown and subs:
        key = unknown[0]
        of = f" of {where}" if path else ""
        raise ConfigError(
            f"{prefix}{'.'.join((*path, key))}: unknown section (the sections{of} are "
            f"{', '.join(subs)}){_hint(key, prefix)}"
        )
    if unknown:
        full = ", ".join(prefix + ".".join((*path, k)) for k in unknown)
        raise ConfigError(f"unknown parameter(s): {full}{''.join(_hint(k, prefix) for k in unknown[:1])}")
    values = {
        k: _updated(getattr(section, k), v, (*path, k), prefix) if k in subs else v
        for k, v in changes.items()
    }
    if "road_width" in values:  # a TOML table or list of pairs
        rw = values["road_width"]
        values["road_width"] = tuple(
            (str(k), float(v)) for k, v in (rw.items() if isinstance(rw, Mapping) else rw)
        )
    try:
        return dataclasses.replace(section, **values)
    except TypeError as exc:  # a value of the wrong kind (a string for a number)
        raise ConfigError(f"{where}: {exc}") from None


_PATHS: dict[str, tuple[str, ...]] = _leaf_paths()
"""Every field's dotted path by its bare name."""
_SECTION_PATH: dict[type, str] = {
    cls: "".join(f"{p}." for p in path) for cls, path, _ in _walk(MatchConfig, ())
}
"""Every section class's dotted path with a trailing dot (``online.region.``; ``""`` for the root)."""


RESULT = "result"
"""A field that changes a result: a rule's threshold or a model constant. docs/tuning.md lists
each with its out-of-fold gain (or how it is estimated or cross-validated)."""
BOUND = "bound"
"""A field that bounds work or memory (a cap, a prune, a search limit): widening it changes no
track's answer on the real tracks, or moves a few within noise out of fold."""
SERVICE = "service"
"""A field that bounds what a caller may send (an imported session's size): not matching."""

_BOUNDS: frozenset[str] = frozenset(
    {
        "model.search_radius",
        "model.max_candidates",
        "online.region.max_hypotheses",
        "online.region.max_hops",
        "online.region.prune_log_ratio",
        "online.region.init_max_radius",
        "online.region.ambiguous_max_radius",
        "online.reinit.far_off",
        "online.evidence.turn_max_samples",
        "online.anchor.align_search_max",
        "online.odometer.odo_scale_max",
        "online.corrections.max_live",
        "online.corrections.trail_max",
        "batch.route.max_route_factor",
        "batch.route.route_slack",
        "batch.track.track_pos_sigma_floor",
        "batch.track.track_heading_sigma_floor_deg",
        "batch.outliers.outlier_distance",
        "batch.outliers.emission_prune",
        "batch.outliers.max_skip",
        "measurement.along_sigma_max",
        "confidence.probability_floor",
    }
)
"""The fields of class :data:`BOUND` by full name."""
_SERVICE_FIELDS: frozenset[str] = frozenset({"online.corrections.max_path_edges"})
"""The fields of class :data:`SERVICE` by full name."""


def field_kinds() -> dict[str, str]:
    """Every field's class by its full name (``online.region.max_hypotheses``): :data:`BOUND`,
    :data:`SERVICE` or, for every other field, :data:`RESULT`."""
    unknown = sorted((_BOUNDS | _SERVICE_FIELDS) - {".".join(p) for p in _PATHS.values()})
    if unknown:
        raise ConfigError(f"classed but not fields: {', '.join(unknown)}")
    out = {}
    for path in _PATHS.values():
        full = ".".join(path)
        out[full] = BOUND if full in _BOUNDS else SERVICE if full in _SERVICE_FIELDS else RESULT
    return out


DEFAULT_CONFIG = MatchConfig()
# batch matching fits whole tracks of plain GPS: a wider default σ, costlier U-turns, thinned fixes,
# and a β that grows with the step (sparse tracks: fixes up to a kilometre apart)
BATCH_CONFIG = DEFAULT_CONFIG.replace(gps_sigma=8.0, uturn_penalty=20.0, beta_per_m=0.04)

UBODT_MAX_BYTES = 1 << 30
"""Default memory budget of a batch run's route table (1 GiB, ``mapmatch match
--ubodt-max-mb``): where a table of the asked bound would not fit, a shorter bound is used
(:meth:`mapmatch.route_table.Ubodt.build`), with the same matches. A resource limit, not a model
parameter: it changes speed and memory, never a result."""
