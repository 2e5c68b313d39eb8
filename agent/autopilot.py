"""The autopilot: the privileged expert that generates training data and sets the bar in evaluation.

It reads the world's ground truth (``env.world``), so it is privileged. Lateral: pure pursuit on the
route's lane centre line (lookahead grows with speed). Longitudinal: a PID speed controller towards a
target speed, capped by an IDM planner that keeps a time headway to whatever is ahead on its own path
(vehicles in its lane, pedestrians in or stepping into it; vehicles in other lanes are ignored),
stops before the stop line on red and on yellow when a comfortable stop is possible, and waits for
oncoming traffic before an unprotected left turn. CARLA's BasicAgent handles lanes, lights and
leaders; this one also handles stop lines and pedestrians. At unsignalled junctions it follows the
world's own rules (``sim.rules``, the ones the NPCs obey and the ego is charged by): a full stop at a
stop line, then its turn in the arrival order and a gap in the priority traffic; at a give-way line a
slow approach and the same gap; on a priority street a left turn waits for oncoming traffic. It keeps
under the posted limits (slowing before a lower one) and stops for people on unsignalled zebras.

Noise injection (off by default): now and then a steering perturbation is added for a moment and the
car recovers from it. ``clean_action`` keeps the expert's own action for the step, which is what a
recording should store as the label (as in the PilotNet and conditional imitation papers).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
from highway_env.road.lane import AbstractLane

from towndrive.agent.decision.pid import PID, STEER_RATE_PER_S  # noqa: F401 (re-exported)
from towndrive.envs.driver_context import DriverContext
from towndrive.sim.objects import LightState
from towndrive.sim.rules import turn_after
from towndrive.sim.spec import CURVE_BRAKE_MPS2, YIELD_APPROACH_MPS
from towndrive.sim.town import Command, Control, lanes_for
from towndrive.sim.traffic import (
    Agents,
    crosswalk_gap,
    curve_speed_limit,
    idm_acceleration,
    junction_gap,
    oncoming_conflict,
    path_gap,
    posted_speed_cap,
)
from towndrive.sim.world import EGO_ID, NextControl, World

if TYPE_CHECKING:
    from towndrive.envs.drive_env import DriveEnv


LEAD_GAP_M = 2.5  # bumper gap kept to a stopped vehicle or pedestrian ahead
STOP_GAP_M = 0.3  # ... and to the stop point before a stop line
HOLD_MARGIN_M = 0.8  # within this of the stopping point at walking pace, brake to a standstill
LANE_CHANGE_ROOM_M = 8.0  # no lane change this near a road's end: a turn from the wrong lane waits short of it


class Autopilot:
    """Privileged expert driver (see module docstring)."""

    name = "autopilot"
    privileged = True

    def __init__(self, target_speed_mps: float = 8.0, noise: bool = False, noise_seed: int = 0,
                 noise_every_s: tuple[float, float] = (4.0, 9.0), noise_steer: float = 0.35,
                 noise_duration_s: float = 0.6, comfortable_brake_mps2: float = 3.5, ignore_lights: bool = False) -> None:
        self.target_speed = target_speed_mps
        self.ignore_lights = ignore_lights  # drive through red lights (to test the red-light checks), like CARLA's
        #                                     BasicAgent(ignore_traffic_lights=True)
        self.noise = noise
        self.noise_seed = noise_seed
        self.noise_every_s = noise_every_s
        self.noise_steer = noise_steer
        self.noise_duration_s = noise_duration_s
        self.comfortable_brake = comfortable_brake_mps2
        self.speed_pid = PID(kp=0.6, ki=0.15, kd=0.0)
        self.env: DriveEnv | None = None
        self.clean_action = np.zeros(2, np.float32)
        self._path_lanes: list[tuple[str, str, int]] = []
        self._last_steer = 0.0
        self._episodes = 0
        self._rng = np.random.default_rng(noise_seed)
        self._next_noise_s = 0.0
        self._noise_until_s = -1.0
        self._noise_sign = 1.0

    def reset(self, env: DriveEnv | Any) -> None:
        self.env = DriverContext.of(env, privileged=True).env
        self.speed_pid.reset()
        self._last_steer = 0.0
        self._rng = np.random.default_rng((self.noise_seed, self._episodes))
        self._episodes += 1
        self._next_noise_s = float(self._rng.uniform(*self.noise_every_s))
        self._noise_until_s = -1.0

    def set_episode_index(self, index: int) -> None:
        """The run's episode ``index`` comes next: its steering noise is drawn from (``noise_seed``, index), so
        an episode is the same whichever worker process runs it (``envs.parallel``)."""
        self._episodes = index

    @property
    def world(self) -> World:
        if self.env is None or self.env.world is None:
            raise RuntimeError("Call reset(env) with a reset environment before act().")
        return self.env.world

    # ------------------------------------------------------------------ decisions
    @staticmethod
    def _lane_on(world: World, edge: tuple[str, str]) -> int:
        """The lane of the route's edge the car is in: the located lane where it lies on that edge, else the
        edge's lane nearest the car (inside a junction, where the car may be located on another move's
        connector, whose lane number says nothing of this edge's)."""
        if world.ego_lane is None:
            return 0
        if world.ego_lane[0][:2] == edge:
            return world.ego_lane[0][2]
        lats = [abs(world.town.lane((*edge, k)).local_coordinates(world.ego.position)[1])
                for k in range(world.town.lane_count(edge))]
        return lats.index(min(lats))

    @staticmethod
    def _turn_lanes(world: World) -> tuple[int, ...] | None:
        """The lanes the announced turn may start from, while the car is on a road and a turn is announced
        (None otherwise: any lane will do)."""
        town = world.town
        edge = world.route[world.route_index]
        if town.lane_info[(*edge, 0)].kind != "road" or world.route_index + 1 >= len(world.route):
            return None
        if world.command() not in (Command.LEFT, Command.RIGHT):
            return None
        return lanes_for(town.lane_info[(*world.route[world.route_index + 1], 0)].command, town.lane_count(edge))

    def wrong_lane_gap(self, world: World, chosen: int) -> float | None:
        """Distance to where a lane change stops being possible, while the announced turn must start from
        another lane than the one the car keeps to (``chosen``: it has not begun to change): the car waits
        there for that lane to clear rather than turn across it."""
        allowed = self._turn_lanes(world)
        if allowed is None or chosen in allowed:
            return None
        lane = world.town.lane((*world.route[world.route_index], chosen))
        s = float(lane.local_coordinates(world.ego.position)[0])
        return max(0.0, lane.length - LANE_CHANGE_ROOM_M - s - world.ego.LENGTH / 2)

    def choose_lane(self, world: World) -> int:
        """The lane to drive in: the current one, unless the announced turn must start from the other lane
        (left turns from lane 0, right turns from lane 1); change when that lane is clear.

        It waits for the route command to announce the turn, as a driver who only hears the command would:
        a lane change the camera sees under "follow" would teach a cloned driver to weave."""
        edge = world.route[world.route_index]
        current = self._lane_on(world, edge)
        allowed = self._turn_lanes(world)
        if allowed is None or current in allowed:
            return current
        target = world.town.lane((*edge, allowed[0]))
        s0 = float(target.local_coordinates(world.ego.position)[0])
        if target.length - s0 < LANE_CHANGE_ROOM_M:
            return current  # too late to change lanes (wrong_lane_gap held the car short of here while it could)
        for v in world.npcs:
            if math.hypot(*(v.position - world.ego.position)) < 20.0:
                s, lat = target.local_coordinates(v.position)
                if abs(lat) < 2.0 and -12.0 < s - s0 < 12.0:
                    return current  # the other lane is not clear yet
        return allowed[0]

    def route_path(self, world: World) -> tuple[list[tuple[AbstractLane, float]], float]:
        """Lanes ahead on the route (in the chosen lane) and the ego's coordinate on the first."""
        lane_id = self.choose_lane(world)
        graph = world.town.network.graph
        path = []
        self._path_lanes = []
        total = 0.0
        index: tuple[str, str, int] | None = None
        for frm, to in world.route[world.route_index:world.route_index + 4]:
            lanes = graph[frm][to]
            index = (frm, to, min(lane_id, len(lanes) - 1)) if index is None else world.town.next_lane(index, (frm, to))
            path.append((lanes[index[2]], total))
            self._path_lanes.append(index)
            total += lanes[0].length
        s0 = float(path[0][0].local_coordinates(world.ego.position)[0])
        return path, s0

    def steer(self, world: World, path: list[tuple[AbstractLane, float]], s0: float) -> float:
        """Pure pursuit from the rear axle towards the lane centre a speed-dependent distance ahead.

        In highway-env's bicycle model (centre of gravity mid-car, tan(delta) = 2 tan(beta)) the rear
        axle drives on an arc of curvature tan(delta) / LENGTH, so delta = atan(2 LENGTH sin(alpha) / ld)."""
        ego = world.ego
        direction = np.array([math.cos(ego.heading), math.sin(ego.heading)])
        rear = ego.position - direction * ego.LENGTH / 2
        lookahead = 3.5 + 0.4 * ego.speed
        target_s = s0 - ego.LENGTH / 2 + lookahead
        lane, offset = path[-1]
        target = lane.position(lane.length, 0.0)
        for lane, offset in path:
            if target_s <= offset + lane.length:
                target = lane.position(max(target_s - offset, 0.0), 0.0)
                break
        dx, dy = target - rear
        alpha = (math.atan2(dy, dx) - ego.heading + math.pi) % (2 * math.pi) - math.pi
        wheel = math.atan2(2.0 * ego.LENGTH * math.sin(alpha), max(math.hypot(dx, dy), 1e-3))
        return max(-1.0, min(1.0, wheel / ego.MAX_STEER_RAD))

    def junction_stop_gap(self, world: World, control: NextControl | None, agents: Agents,
                          zebra: float | None) -> float | None:
        """At an unsignalled junction ahead (``control``: the next one on the route): the distance to where the
        car must stop, if the rules say wait (``sim.traffic.junction_gap``: the world's rules, the NPCs' too),
        else None."""
        if control is None or control.control == Control.SIGNAL:
            return None
        entry = world.town.entries[control.entry]
        if control.distance_m < -0.3:
            return None  # the bumper is over the line: clear the junction
        index = world.route.index(entry.edge, world.route_index)
        turn = turn_after(world.town, world.route, index)
        gap = max(control.distance_m - 0.8, 0.0)
        zebra_beyond = None if zebra is None else zebra - 0.8
        return junction_gap(world.town, world.junctions, EGO_ID, entry, turn, gap, agents, zebra_beyond)

    def stop_gap(self, world: World, control: NextControl | None, agents: Agents) -> float | None:
        """Distance to where the car must stop for a light or an unprotected left turn, if it must
        (``control``: the next junction entry on the route)."""
        if control is not None and control.control != Control.SIGNAL:
            return None  # an unsignalled junction comes first: junction_stop_gap
        light = world.next_light()
        if light is None or self.ignore_lights:
            return None
        speed = world.ego.speed
        gap = max(light.distance_m - 0.8, 0.0)
        if light.state == LightState.RED:
            return gap
        if light.state == LightState.YELLOW and speed ** 2 / (2 * max(light.distance_m, 0.1)) < self.comfortable_brake:
            return gap
        if world.command() == Command.LEFT and light.distance_m > -0.5:
            approach = world.town.approaches[light.approach]
            if oncoming_conflict(world.town, approach, agents, EGO_ID):
                return gap
        return None

    def act(self, observation: dict[str, Any]) -> np.ndarray:
        world = self.world
        ego = world.ego
        dt = world.config.dt_s
        path, s0 = self.route_path(world)
        steer = self.steer(world, path, s0)
        # Gentle hands: at most STEER_RATE_PER_S of the full range per second (smooth labels for cloning).
        step = STEER_RATE_PER_S * dt
        steer = min(self._last_steer + step, max(self._last_steer - step, steer))
        self._last_steer = steer
        # Longitudinal: PID to the target speed, capped by the IDM planner's acceleration.
        cruise = min(self.target_speed, curve_speed_limit(path, s0))
        if world.town.speed_limits_kmh:
            cruise = min(cruise, posted_speed_cap(world.town, path, self._path_lanes, s0))
        control = world.next_control()  # the next junction entry (asked once a step)
        give_way = control is not None and control.control == Control.YIELD and control.distance_m > 0.0
        if give_way and not self.ignore_lights:  # a give-way line: slow enough to stop at it after a last look
            cruise = min(cruise, math.sqrt(YIELD_APPROACH_MPS ** 2 + 2.0 * CURVE_BRAKE_MPS2 * control.distance_m))
        accel = self.speed_pid(cruise - ego.speed, dt) * ego.MAX_ACCEL_MPS2
        agents = world.agents()
        lookahead = 15.0 + 3.0 * ego.speed
        gap, lead_speed = path_gap(path, s0, ego.LENGTH / 2, agents, EGO_ID, ego.position, lookahead)
        zebra = crosswalk_gap(world.town, path, self._path_lanes, s0, ego.LENGTH / 2, agents, lookahead)
        if zebra is not None and (gap is None or zebra < gap):
            gap, lead_speed = zebra, 0.0
        hold = False  # IDM creeps towards a standstill; near the stopping point, brake and hold instead
        if gap is not None:
            accel = min(accel, idm_acceleration(ego.speed, self.target_speed, gap, ego.speed - lead_speed,
                                                min_gap_m=LEAD_GAP_M))
            hold |= gap < LEAD_GAP_M + HOLD_MARGIN_M and lead_speed < 0.5
        stop = self.stop_gap(world, control, agents)
        wrong = self.wrong_lane_gap(world, self._path_lanes[0][2])
        if wrong is not None:
            stop = wrong if stop is None else min(stop, wrong)
        if not self.ignore_lights:  # the signs too: an autopilot that ignores lights tests the infraction checks
            wait = self.junction_stop_gap(world, control, agents, zebra)
            if wait is not None:
                stop = wait if stop is None else min(stop, wait)
        if stop is not None:
            accel = min(accel, idm_acceleration(ego.speed, self.target_speed, stop, ego.speed, min_gap_m=STOP_GAP_M))
            hold |= stop < STOP_GAP_M + HOLD_MARGIN_M
        if world.route_done or (hold and ego.speed < 1.0):
            accel = -ego.MAX_BRAKE_MPS2
        throttle = accel / ego.MAX_ACCEL_MPS2 if accel >= 0 else accel / ego.MAX_BRAKE_MPS2
        self.clean_action = np.array([steer, max(-1.0, min(1.0, throttle))], np.float32)
        return self._with_noise(self.clean_action.copy(), world.time_s)

    def _with_noise(self, action: np.ndarray, now_s: float) -> np.ndarray:
        """Add a short steering perturbation now and then (only when ``noise`` is on)."""
        if not self.noise:
            return action
        if now_s >= self._next_noise_s and now_s > self._noise_until_s:
            self._noise_until_s = now_s + self.noise_duration_s
            self._noise_sign = 1.0 if self._rng.random() < 0.5 else -1.0
            self._next_noise_s = now_s + self.noise_duration_s + float(self._rng.uniform(*self.noise_every_s))
        if now_s < self._noise_until_s:
            action[0] = float(np.clip(action[0] + self._noise_sign * self.noise_steer, -1.0, 1.0))
        return action
