"""Road-design priors: a town style's, the agent's turn arc from them, and their correction by measurement."""

from __future__ import annotations

import math

import numpy as np
import pytest

from towndrive.agent.decision.junction import turn_path
from towndrive.agent.decision.priors import fused
from towndrive.sim.road_priors import road_priors
from towndrive.sim.spec import ROAD
from towndrive.sim.town import Command, TownConfig
from towndrive.sim.world import cached_town


def test_a_prior_with_no_spread_is_the_design_and_one_with_a_spread_moves_towards_the_measurement() -> None:
    assert fused(12.0, 0.0, 19.0, 0.5) == 12.0
    assert fused(12.0, 1.0, None, 0.5) == 12.0
    assert fused(12.0, 1.0, 14.0, 1.0) == pytest.approx(13.0)
    assert fused(12.0, 2.0, 14.0, 1.0) == pytest.approx(12.0 + 2.0 * 4.0 / 5.0)


def test_the_classic_style_s_priors_are_the_classic_design_and_a_styled_one_s_are_measured_on_its_towns() -> None:
    assert road_priors("classic") is ROAD
    downtown = road_priors("downtown")
    assert downtown == road_priors("downtown")  # the same towns, the same numbers
    assert downtown.stop_line_setback_m > ROAD.stop_line_setback_m + 4.0 and downtown.stop_line_setback_sd_m > 0.5
    assert downtown.left_turn_radius_m is not None and downtown.right_turn_radius_m is not None
    assert 0.0 < downtown.zebra_to_centre_sd_m < downtown.stop_line_setback_sd_m  # the zebra is the better anchor
    assert downtown.signal_head_height_sd_m > 0.3  # mast arms and posts


def test_a_turn_with_a_radius_runs_straight_past_the_bar_then_bends_into_the_lane_turned_into() -> None:
    for command, side in ((2, 1.0), (1, -1.0)):
        reach = 18.0 - 1.75 if command == 2 else 18.0 + 1.75
        path, arc_end = turn_path(command, 18.0, 1.75, 0.5, 9.0)
        steps = np.hypot(*np.diff(path, axis=0).T)
        assert steps.max() < 0.25  # one continuous polyline
        k = int(round(arc_end / 0.2))
        assert path[k - 1] == pytest.approx([0.5 + reach, side * 9.0], abs=0.2)  # the arc ends in the lane...
        assert path[-1][0] == pytest.approx(0.5 + reach)  # ... and follows it
        lead = path[(path[:, 0] > 0.5) & (path[:, 0] < 0.5 + reach - 9.0 - 0.2)]
        assert len(lead) > 10 and np.abs(lead[:, 1]).max() < 1e-9  # straight on before the arc
        # a radius wider than the lane turned into allows is the quarter circle from the bar
        assert np.array_equal(turn_path(command, 18.0, 1.75, 0.5, 40.0)[0], turn_path(command, 18.0, 1.75, 0.5)[0])


def _connector_deviation(style: str, town_seed: int, road) -> list[float]:
    """For each signalled or sign-controlled arm of two lanes in a town, how far (m) the agent's turn arc from
    ``road``'s priors (placed at the arm's stop bar) strays from the town's own connector, left and right."""
    town = cached_town(TownConfig.of_style(style), town_seed)
    out = []
    for entry in town.entries:
        if entry.lane_count != 2:
            continue
        t = np.array([math.cos(entry.travel_heading), math.sin(entry.travel_heading)])
        right = np.array([-t[1], t[0]])
        for command, k in ((Command.LEFT, 0), (Command.RIGHT, 1)):
            conn = next((i for i, info in town.lane_info.items() if i[0] == entry.edge[1] and i[2] == k
                         and info.kind == "connector" and info.command == command), None)
            if conn is None:
                continue
            approach = town.lane((entry.edge[0], entry.edge[1], k))
            origin = approach.position(approach.length, 0.0)
            lane = town.lane(conn)
            pts = np.array([lane.position(s, 0.0) for s in np.linspace(0.0, lane.length, 40)])
            rel = np.stack([(pts - origin) @ t, (pts - origin) @ right], axis=1)
            radius = road.left_turn_radius_m if command == Command.LEFT else road.right_turn_radius_m
            path, _ = turn_path(int(command), road.stop_line_setback_m, (k + 0.5) * road.lane_width_m,
                                road.stop_bar_depth_m, radius)
            gap = np.sqrt(((rel[:, None, :] - path[None, :, :]) ** 2).sum(-1)).min(axis=1)
            out.append(float(gap.max()))
    return out


def test_in_a_styled_town_the_style_s_priors_place_the_turns_where_the_classic_design_cannot() -> None:
    """Downtown's stop bars stand 16-21 m from the junction's centre, and its turns run straight on past the bar
    before they bend: the classic design's quarter circle from the bar strays 7-9 m from the town's turns (median
    over a town's turns), the style's priors (before any measurement) 2-3 m."""
    style = _connector_deviation("downtown", 7, road_priors("downtown"))
    classic = _connector_deviation("downtown", 7, ROAD)
    assert len(style) > 20
    assert float(np.median(classic)) > 6.0
    assert float(np.median(style)) < 3.0
