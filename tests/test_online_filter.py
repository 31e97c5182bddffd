"""The generic filter step knows nothing of roads; the road model's scorers work alone."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pytest
from service_util import city

from graph.rules import legal_moves
from mapmatch.config import DEFAULT_CONFIG
from mapmatch.online.filter import best, filter_step, keep_best, normalise
from mapmatch.online.road import RoadModel
from mapmatch.online.state import Hypothesis


@dataclass
class Point:
    """A hypothesis of a 1-D filter: a position and a log-probability, no road at all."""

    s: float
    logp: float = 0.0


def test_filter_step_on_a_line_without_roads() -> None:
    hyps = [Point(0.0), Point(10.0), Point(20.0)]
    z = 11.0  # observation; each hypothesis moves 1 m towards it and is scored by its distance

    def place(ps: Sequence[Point]) -> list[tuple[float, float]]:
        out = []
        for p in ps:
            before = p.s
            p.s += math.copysign(1.0, z - p.s)
            out.append((-0.5 * (p.s - z) ** 2, -abs(p.s - before - 1.0)))
        return out

    filter_step(hyps, weight=0.5, place=place)
    assert [p.s for p in hyps] == [1.0, 11.0, 19.0]
    # weight × (place + turn): the one moving away from z also pays its turn score
    assert [p.logp for p in hyps] == [0.5 * -50.0, 0.0, 0.5 * (-32.0 - 2.0)]
    kept = normalise(hyps, prune_log_ratio=20.0)
    assert best(kept).s == 11.0 and best(kept).logp == 0.0 and len(kept) == 2
    keep_best(kept, 1)
    assert [p.s for p in kept] == [11.0]


def test_a_single_hypothesis_is_not_weighed() -> None:
    one = [Point(3.0, logp=-2.0)]
    filter_step(one, weight=1.0, place=lambda ps: [(-100.0, -100.0)] * len(ps))
    assert one[0].logp == -2.0


def test_road_scorers_alone() -> None:
    amap = city()
    road = RoadModel(amap.graph)
    e = amap.edge("a", "b")
    # emission: best on the road, heading along it; worse off it or against it
    on = road.emission(0.0, 5.0, road.bstart[e], road.bstart[e], 8.0)
    assert on > road.emission(5.0, 5.0, road.bstart[e], road.bstart[e], 8.0)
    assert on > road.emission(0.0, 5.0, (road.bstart[e] + 180.0) % 360.0, road.bstart[e], 8.0)
    # transition: progress matching the odometer is best
    from mapmatch.online.params import place_params
    from mapmatch.online.placement import turn_score
    from mapmatch.online.state import FixBias, Step

    step = Step(
        time=1.0, x=0.0, y=0.0, sigma=5.0, heading=math.nan, kappa=0.0, travelled=10.0, odo=10.0,
        odo_known=True, dt=1.0, gps=True, weight=1.0, stopped=False, r_a=10.0, dr=0.0, bias=FixBias(),
        odo_sigma=0.02,
    )  # fmt: skip
    assert road.transition(10.0, step, DEFAULT_CONFIG) == 0.0
    assert road.transition(20.0, step, DEFAULT_CONFIG) == pytest.approx(-10.0 / DEFAULT_CONFIG.model.beta)
    # turn: a straight path predicts no heading change, so an observed 90° turn costs
    b = amap.edge("b", "c")
    h = Hypothesis([e, b], 1, 10.0, road.elen[e] + 10.0, 0.0, [0.0, 1.0], bearing=road.bstart[b])

    def turn(observed: float, covered: float) -> float:
        p = place_params(step, DEFAULT_CONFIG, turn_obs=observed, covered=covered)
        pos = (h.k, h.off, h.s, h.dist, h.px, h.py, h.bearing)
        return float(turn_score(road.arrays, p, np.array(h.edges, dtype=np.int64), pos, h.s - 10.0))

    assert turn(0.0, 30.0) == 0.0
    assert turn(90.0, 30.0) < -1.0
    assert turn(90.0, 5.0) == 0.0  # too little covered


def test_legal_moves_table_u_turn_policies() -> None:
    amap = city()
    g = amap.graph
    junction = legal_moves(g, uturns="junction")
    never = legal_moves(g, uturns="never")
    ab, ba = amap.edge("a", "b"), amap.edge("b", "a")
    # at b three roads meet: turning back is a move, penalised; under "never" it is none
    assert ba in junction.after(ab) and junction.uturn[junction.ptr[ab] + junction.after(ab).index(ba)]
    assert ba not in never.after(ab) and not never.uturn.any()
    road = RoadModel(g)
    assert (ba, -DEFAULT_CONFIG.model.uturn_penalty) in road.children(ab, DEFAULT_CONFIG)
