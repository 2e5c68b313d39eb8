"""A simple privileged lane keeper: pure pursuit along the route's lane centres, a proportional
speed controller, and stops for red lights and for whatever is ahead on its path.

It reads the world's ground truth (so it is privileged and says so); it stands in for the
autopilot of the drivers issue in the README's demo drive.
"""

from __future__ import annotations

import math

import numpy as np

from sim.objects import LightState
from sim.traffic import idm_acceleration, path_gap
from sim.world import EGO_ID, World


class PrivilegedLaneKeeper:
    """Follows the world's route; ``act(world)`` returns ``[steer, throttle_brake]``."""

    privileged = True
    name = "lane_keeper"

    def __init__(self, target_speed_mps: float = 8.0, lookahead_min_m: float = 5.0, lookahead_gain_s: float = 0.6) -> None:
        self.target_speed = target_speed_mps
        self.lookahead_min = lookahead_min_m
        self.lookahead_gain = lookahead_gain_s

    def reset(self) -> None:
        """Stateless; present for the driver interface."""

    def _route_path(self, world: World) -> tuple[list, float, int]:
        """Lanes ahead on the route (lane id kept from the current lane) and the ego's s on the first."""
        lane_id = world.ego_lane[0][2] if world.ego_lane is not None else 0
        town = world.town
        path = []
        total = 0.0
        for frm, to in world.route[world.route_index:world.route_index + 4]:
            lane = town.network.graph[frm][to][min(lane_id, len(town.network.graph[frm][to]) - 1)]
            path.append((lane, total))
            total += lane.length
        s0 = float(path[0][0].local_coordinates(world.ego.position)[0])
        return path, s0, lane_id

    def act(self, world: World) -> np.ndarray:
        ego = world.ego
        path, s0, _ = self._route_path(world)
        lookahead = self.lookahead_min + self.lookahead_gain * ego.speed
        target_s = s0 + lookahead
        target = None
        for lane, offset in path:
            if target_s <= offset + lane.length:
                target = lane.position(target_s - offset, 0.0)
                break
        if target is None:
            lane, offset = path[-1]
            target = lane.position(lane.length, 0.0)
        # Pure pursuit on the rear axle (highway-env's bicycle uses the centre; close enough here).
        dx, dy = target - ego.position
        alpha = math.atan2(dy, dx) - ego.heading
        alpha = (alpha + math.pi) % (2 * math.pi) - math.pi
        dist = max(math.hypot(dx, dy), 1e-3)
        wheel = math.atan2(2.0 * ego.LENGTH / 2 * math.sin(alpha), dist)
        steer = float(np.clip(wheel / ego.MAX_STEER_RAD, -1.0, 1.0))
        # Longitudinal: IDM towards the target speed, the path's leader and a red/yellow stop line.
        agents = world.agents()
        gap, lead_speed = path_gap(path, s0, ego.LENGTH / 2, agents, EGO_ID, ego.position, 15.0 + 3.0 * ego.speed)
        acc = idm_acceleration(ego.speed, self.target_speed, gap, ego.speed - lead_speed)
        light = world.next_light()
        if light is not None and light.state != LightState.GREEN:
            comfortable = ego.speed ** 2 / (2 * max(light.distance_m, 0.1)) < 3.5
            if light.state == LightState.RED or comfortable:
                acc = min(acc, idm_acceleration(ego.speed, self.target_speed, max(light.distance_m - 0.8, 0.0),
                                                ego.speed, min_gap_m=0.5))
        throttle = acc / ego.MAX_ACCEL_MPS2 if acc >= 0 else acc / ego.MAX_BRAKE_MPS2
        return np.array([steer, float(np.clip(throttle, -1.0, 1.0))], dtype=np.float32)
