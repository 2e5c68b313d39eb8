"""Why the ego stands still, from ground truth: the evaluator's measure of false holds.

A driver that stops for a person nobody is standing in, or waits at a junction nobody blocks, loses
only route completion, which a driving score blends with everything else. The evaluator therefore
asks, for every step the car stands, whether the world gives it a reason to: someone or something on
its path within ``STANDING_LOOKAHEAD_M``, someone on a zebra it is about to cross, a red or yellow light
at a stop line just ahead, or oncoming traffic across an unprotected left turn. A standstill with none
of these is "standing with nothing in the path"; ``envs.metrics`` adds it up per episode.

The tests here are deliberately generous to the driver (a wider corridor and a longer look than the
privileged autopilot drives with), so that a step counted as a false hold is one no careful driver
would call a reason.
"""

from __future__ import annotations

from towndrive.sim.objects import LightState
from towndrive.sim.town import Approach, Command, Control
from towndrive.sim.traffic import crosswalk_gap, oncoming_conflict, path_gap
from towndrive.sim.world import EGO_ID, World

STANDING_SPEED_MPS = 0.1  # below this the car stands
STANDING_LOOKAHEAD_M = 12.0  # an agent or an occupied zebra this far ahead of the bumper is a reason to stand
STANDING_LIGHT_M = 15.0  # a red or yellow stop bar this close ahead is a reason to stand
STOPPING_CONTROLS = (Control.STOP, Control.ALL_WAY_STOP, Control.YIELD)  # lines at which waiting is the rule
STANDING_LATERAL_M = 3.0  # half-width of the corridor in which a vehicle or pedestrian counts


def standing_reason(world: World) -> str | None:
    """What in the world holds the standing ego up ("vehicle or pedestrian", "crosswalk", "red light",
    "yellow light", "stop sign", "give way", "oncoming traffic", "off road"), or None when nothing does. Call
    it when the car stands."""
    ego = world.ego
    if world.ego_lane is None:
        return "off road"
    light = world.next_light(horizon_m=STANDING_LIGHT_M)
    if light is not None and light.state != LightState.GREEN and light.distance_m > -1.0:
        return f"{light.state.name.lower()} light"
    control = world.next_control(horizon_m=STANDING_LIGHT_M)
    if control is not None and control.control in STOPPING_CONTROLS and control.distance_m > -1.0:
        return "stop sign" if control.control != Control.YIELD else "give way"  # its turn, a gap: sim.rules
    path, path_lanes, s0 = _route_path(world)
    agents = world.agents()
    gap, _ = path_gap(path, s0, ego.LENGTH / 2, agents, EGO_ID, ego.position, STANDING_LOOKAHEAD_M,
                      vehicle_lateral_m=STANDING_LATERAL_M, pedestrian_lateral_m=STANDING_LATERAL_M)
    if gap is not None and gap < STANDING_LOOKAHEAD_M:
        return "vehicle or pedestrian"
    zebra = crosswalk_gap(world.town, path, path_lanes, s0, ego.LENGTH / 2, agents, STANDING_LOOKAHEAD_M)
    if zebra is not None:
        return "crosswalk"
    approach = _turn_approach(world)
    if approach is not None and _turning_left_at(world) and oncoming_conflict(world.town, approach, agents, EGO_ID):
        return "oncoming traffic"
    return None


def _route_path(world: World) -> tuple[list, list[tuple[str, str, int]], float]:
    """The lanes ahead on the route, starting with the one the car is on, in its lane number."""
    assert world.ego_lane is not None
    graph = world.town.network.graph
    here, k = world.ego_lane[0][:2], world.ego_lane[0][2]
    edges = world.route[world.route_index:world.route_index + 3]
    edges = [here, *edges] if here not in edges else edges[edges.index(here):]
    path, lanes, total = [], [], 0.0
    index: tuple[str, str, int] | None = None
    for frm, to in edges:
        options = graph[frm][to]
        index = (frm, to, min(k, len(options) - 1)) if index is None else world.town.next_lane(index, (frm, to))
        lane = options[index[2]]
        path.append((lane, total))
        lanes.append(index)
        total += lane.length
    s0 = float(path[0][0].local_coordinates(world.ego.position)[0])
    return path, lanes, s0


def _turn_approach(world: World) -> Approach | None:
    """The signalled approach of the junction the car is turning at (the route edge before the connector)."""
    for edge in world.route[max(0, world.route_index - 1):world.route_index + 2]:
        ap = world.town.approach_for_edge(edge)
        if ap is not None:
            return ap
    return None


def _turning_left_at(world: World) -> bool:
    """Whether the car is at or in a junction with a left turn on its route there."""
    info = world.town.lane_info
    for edge in world.route[world.route_index:world.route_index + 2]:
        lane = info.get((*edge, 0))
        if lane is not None and lane.kind == "connector" and lane.command == Command.LEFT:
            return True
    return False
