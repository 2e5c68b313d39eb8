"""The road-design priors of a town style: what a driver who knows the kind of place, but not the town, assumes.

Why: the camera-only agent places junction turns and picks its traffic light from road-design numbers (how far the
stop bar stands from the junction's centre, how wide the turns are, where the signal heads hang). A real car knows
its country's road design, not each junction; a town style is such a design. Its priors are the statistics of the
style's junctions in the training towns (``sim.splits``): the mean of each number and how far it spreads, which the
agent then corrects by what it measures (``agent.decision.junction``, ``agent.decision.our_light``). The classic
style is the design the agent was built on (``sim.spec.ROAD``); its numbers stay exact.
"""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache

import numpy as np
from highway_env.road.lane import AbstractLane

from towndrive.sim.fillet_lane import FilletLane
from towndrive.sim.geometry import wrap_to_pi
from towndrive.sim.spec import ROAD, CrossStreetOdds, RoadDesign, SignalMount, TurnRadius, TurnReach
from towndrive.sim.splits import split_towns
from towndrive.sim.town import Command, Control, Crosswalk, Town, TownConfig, generate_town
from towndrive.sim.town_style import CLASSIC, style_named

PRIOR_TOWNS = 4  # training towns a style's priors are measured on (their junctions number in the hundreds)
# A kind of junction seen at only a few of them, all alike, is not certain: its two-lane share is the posterior mean
# with the style's share over every kind as a prior worth this many junctions (a count of 0 or 1 then leaves the
# other possible, as hedged turns need; ``sim.spec.COUNT_DOUBT``)
ODDS_PRIOR_JUNCTIONS = 2.0
_KIND = {Control.SIGNAL: "signal", Control.STOP: "stop", Control.ALL_WAY_STOP: "stop", Control.YIELD: "yield",
         Control.PRIORITY: "none"}


def control_kind(control: Control) -> str:
    """What governs a junction's arm as a driver sees it (``sim.spec.CONTROL_KINDS``): an all-way stop's signs
    are a stop sign's."""
    return _KIND[control]


def zebra_far_along(crosswalk: Crosswalk, origin: np.ndarray, heading: float) -> float:
    """How far along the line from ``origin`` at ``heading`` the crosswalk's far edge lies (where the line
    crosses it: with a cross street that leans, not the crosswalk's farthest corner)."""
    t = np.array([np.cos(heading), np.sin(heading)])
    poly = np.asarray(crosswalk.polygon, float)
    edges = [(poly[i], poly[(i + 1) % 4]) for i in range(4)]
    long_edges = sorted(edges, key=lambda e: -float(np.hypot(*(e[1] - e[0]))))[:2]  # its edges across the road
    p, q = max(long_edges, key=lambda e: float(((e[0] + e[1]) / 2 - origin) @ t))
    along, _ = np.linalg.solve(np.column_stack([t, p - q]), p - origin)
    return float(along)


def exit_crossing(lane: AbstractLane, origin: np.ndarray, heading: float) -> float:
    """How far along the line from ``origin`` at ``heading`` the centre line of the lane a turn ``lane`` goes into,
    continued back from the turn's end, crosses it."""
    t = np.array([np.cos(heading), np.sin(heading)])
    end = lane.position(lane.length, 0.0) - origin
    turn = wrap_to_pi(lane.heading_at(lane.length) - heading)
    return float(end @ t) - float(end @ np.array([-t[1], t[0]])) / np.tan(turn)


def junction_samples(town: Town) -> dict[str, list[float]]:
    """Each junction arm's road-design numbers in one town (the quantities ``RoadDesign`` holds)."""
    out: dict[str, list[float]] = {k: [] for k in ("setback", "zebra", "left", "right", "width", "kerb_reach",
                                                   "far_shift", "far_turn")}
    zebra_at = {(cw.node, cw.arm): cw for cw in town.crosswalks}
    depth = ROAD.stop_bar_depth_m
    for entry in town.entries:
        centre = town.node_position(entry.node)
        t = np.array([np.cos(entry.travel_heading), np.sin(entry.travel_heading)])
        right = np.array([-t[1], t[0]])
        bar_near = float((centre - entry.line_center) @ t)  # bar's near edge to the junction centre
        out["setback"].append(bar_near - depth)
        cw = zebra_at.get((entry.node, entry.arm))
        if cw is not None:
            out["zebra"].append(float(np.min((centre - cw.polygon) @ t)))  # its far edge, to the centre
        cross_lanes = None
        for idx, info in town.lane_info.items():
            if idx[0] != entry.edge[1] or info.kind != "connector":
                continue
            lane = town.lane(idx)
            radius = _turn_radius(lane)
            turns_from = 0 if info.command == Command.LEFT else entry.lane_count - 1
            if info.command in (Command.LEFT, Command.RIGHT) and idx[2] == turns_from:
                # the cross street's lanes each way, and where the lane turned into crosses ours beyond the zebra
                exit_edge = (idx[1], next(iter(town.network.graph[idx[1]])))
                cross_lanes = town.lane_count(exit_edge)
                if cw is not None:
                    start = lane.position(0.0, 0.0)  # our lane's centre at the bar's far edge
                    side = "left" if info.command == Command.LEFT else "right"
                    out.setdefault(f"reach:{cross_lanes}:{side}", []).append(
                        exit_crossing(lane, start, entry.travel_heading)
                        - zebra_far_along(cw, start, entry.travel_heading))
                if info.command == Command.RIGHT:  # its radius, by both roads' lanes each way
                    out.setdefault(f"radius:{entry.lane_count}:{cross_lanes}", []).append(radius)
            if info.command == Command.STRAIGHT:
                # where the lane straight on leads, across from our lane carried on, and how far it is turned
                start, end = lane.position(0.0, 0.0), lane.position(lane.length, 0.0)
                out["far_shift"].append(float((end - start) @ right))
                out["far_turn"].append(float(np.degrees(wrap_to_pi(lane.heading_at(lane.length)
                                                                   - entry.travel_heading))))
            if info.command == Command.LEFT and idx[2] == 0:
                out["left"].append(radius)
            elif info.command == Command.RIGHT and idx[2] == entry.lane_count - 1:
                out["right"].append(radius)
                # where the lane turned into crosses the approach lane's centre line, from the bar's far edge (the
                # agent's arc turns by the cross street's angle, measured, into that line)
                out["kerb_reach"].append(exit_crossing(lane, entry.line_center, entry.travel_heading) - depth)
        if cross_lanes is not None:
            out.setdefault(f"odds:{control_kind(entry.control)}:{entry.lane_count}", []).append(
                float(cross_lanes >= 2))
        if entry.approach >= 0:
            ap = town.approaches[entry.approach]
            # across the incoming lanes from their middle (positive: right), then from our lane's centre
            # (the agent drives the inner lane of two, the middle of one)
            lanes_w = entry.lane_count * town.lane_width
            for key, value in (("beyond", float((ap.light_head - entry.line_center) @ t) - depth),
                               ("lateral", float((ap.light_head - entry.line_center) @ right) + lanes_w / 2
                                - 0.5 * town.lane_width), ("height", float(ap.head_height_m))):
                out.setdefault(f"{ap.mount}:{key}", []).append(value)
    out["width"].append(float(town.lane_width))
    return out


def _turn_radius(lane: object) -> float:
    if isinstance(lane, FilletLane):
        return float(lane.tightest_turn()[0])
    return float(getattr(lane, "radius", np.inf))


def cross_street_odds(samples: dict[str, np.ndarray]) -> tuple[CrossStreetOdds, ...]:
    """The odds of a two-lane cross street per kind of junction (``odds:<control>:<our lanes>``: 1 where the cross
    street had two lanes, else 0), each kind's share drawn towards the share over all kinds as far as it was seen
    at few junctions (``ODDS_PRIOR_JUNCTIONS``)."""
    if not samples:
        return ()
    overall = float(np.mean(np.concatenate(list(samples.values()))))
    return tuple(CrossStreetOdds(k.split(":")[1], int(k.split(":")[2]),
                                 round((float(np.sum(v)) + ODDS_PRIOR_JUNCTIONS * overall)
                                       / (len(v) + ODDS_PRIOR_JUNCTIONS), 3), len(v))
                 for k, v in sorted(samples.items()))


@lru_cache(maxsize=8)
def road_priors(style: str, towns: int = PRIOR_TOWNS) -> RoadDesign:
    """The road design a driver assumes in towns of ``style`` (module docstring): the classic design for the
    classic style, else the mean and spread of the style's junctions in its first ``towns`` training towns."""
    if style_named(style).name == CLASSIC.name:
        return ROAD
    samples: dict[str, list[float]] = {}
    for seed in split_towns("train", towns):
        for k, v in junction_samples(generate_town(TownConfig.of_style(style), seed=seed)).items():
            samples.setdefault(k, []).extend(v)
    a = {k: np.asarray(v, float) for k, v in samples.items()}

    def mean(k: str) -> float:
        return round(float(np.mean(a[k])), 2)

    def sd(k: str) -> float:
        return round(float(np.std(a[k])), 2)

    # one mode per kind of mount (where heads hang is a kind, not a spread)
    mounts = {m: SignalMount(mean(f"{m}:beyond"), mean(f"{m}:lateral"), mean(f"{m}:height"))
              for m in {k.split(":")[0] for k in a if k.endswith(":beyond")}}
    main = mounts.get("mast_arm")
    mast_arm = {} if main is None else {"light_beyond_stop_line_m": main.beyond_stop_line_m,
                                        "light_lateral_m": main.lateral_m, "signal_head_height_m": main.height_m}
    # the turns beyond the zebra, by the cross street's lanes each way; the odds of a two-lane cross street by kind
    reaches = tuple(TurnReach(n, mean(f"reach:{n}:left"), mean(f"reach:{n}:right")) for n in (1, 2)
                    if f"reach:{n}:left" in a and f"reach:{n}:right" in a)
    odds = cross_street_odds({k: v for k, v in a.items() if k.startswith("odds:")})
    radii = tuple(TurnRadius(int(k.split(":")[1]), int(k.split(":")[2]), mean(k)) for k in sorted(a)
                  if k.startswith("radius:"))
    return replace(ROAD, lane_width_m=mean("width"), lane_width_sd_m=sd("width"),
                   stop_line_setback_m=mean("setback"), stop_line_setback_sd_m=sd("setback"),
                   zebra_to_centre_m=mean("zebra"), zebra_to_centre_sd_m=sd("zebra"),
                   left_turn_radius_m=mean("left"), right_turn_radius_m=mean("right"), right_turn_radii=radii,
                   kerb_lane_reach_m=mean("kerb_reach"), kerb_lane_reach_sd_m=sd("kerb_reach"),
                   turn_reaches=reaches, cross_street_odds=odds,
                   far_lane_shift_sd_m=sd("far_shift"), far_lane_turn_sd_deg=sd("far_turn"),
                   **mast_arm, other_signal_mounts=tuple(mounts[m] for m in sorted(mounts) if m != "mast_arm"))
