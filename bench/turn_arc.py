"""The agent's junction arc alone, turn by turn: how far outside its lanes the car gets before the arc lets go.

Why: in the styled towns most take-overs come in junction turns, and a closed-loop evaluation mixes the arc's
error with PilotNet's, the stop bar's reading and traffic. Here each turn of a town is driven on the world's own
bicycle model by the agent's junction guidance alone (``agent.decision.junction``), from 2.3 m before the stop
bar with the bar's distance given exactly and no traffic, at the turn speed, until the arc hands over to the camera
(or the car is on the road turned into). The bar's distance, the zebra's far edge and the slope of its edges (the
cross street's direction, ``Zebra.tilt``) are given as the detectors would report them, read from the town;
``--no-tilt`` leaves the slope out (the arc then assumes a square junction). In the turn the camera's frames are
rendered and the road turned into is read from them as the agent does (``agent.perception.exit_line``); once read,
the arc leads the whole turn; ``--no-exit`` leaves that out. The figure per turn is the largest "outside its lanes"
distance, the safety driver's measure (a take-over beyond 1 m); 9 means the car left the road.

  python bench/turn_arc.py --style suburb --towns 4000,4001 --command right
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from towndrive.agent.drivers import make_driver  # noqa: E402
from towndrive.agent.perception.stop_line import StopLine  # noqa: E402
from towndrive.envs.drive_env import DriveConfig, DriveEnv  # noqa: E402
from towndrive.sim.road_priors import control_kind, road_priors, zebra_far_along  # noqa: E402
from towndrive.sim.spec import ROAD  # noqa: E402
from towndrive.sim.town import Command, TownConfig  # noqa: E402
from towndrive.sim.world import World, WorldConfig, cached_town  # noqa: E402

BAR_AHEAD_M = 5.5  # the bumper's distance to the stop bar when the turn is placed (near enough to read the zebra's slope)
OFF_ROAD = 9.0


def drive_turn(style: str, town_seed: int, entry_index: int, command: int,
               tilt: bool = True, kind: bool = True, exit_read: bool = True,
               inner: bool = False) -> tuple[int, int, float] | None:
    """(our lanes, the cross street's, the largest outside-the-lanes distance) of one turn, from the lane a driver
    keeps to for it (left turns the inner lane, right turns the kerb lane) or, with ``inner``, from the inner lane
    (a right turn whose lane change was held); None if the entry has no such turn (or, with ``inner``, no lane but
    the kerb lane)."""
    config = DriveConfig(world=WorldConfig(town=TownConfig.of_style(style)), render_camera=exit_read)
    town = cached_town(config.world.town, town_seed)
    entry = town.entries[entry_index]
    if inner and entry.lane_count < 2:
        return None
    k = 0 if command == Command.LEFT or inner else entry.lane_count - 1
    connector = next((idx for idx, info in town.lane_info.items() if idx[0] == entry.edge[1] and idx[2] == k
                      and info.kind == "connector" and info.command == command), None)
    if connector is None:
        return None
    goal = (connector[1], next(iter(town.network.graph[connector[1]])))
    lane = town.network.graph[entry.edge[0]][entry.edge[1]][k]
    world = World(town, replace(config.world, npc_count=0, pedestrian_count=0), seed=0,
                  start=(entry.edge[0], entry.edge[1], k), start_s=lane.length - 0.5 - BAR_AHEAD_M - 2.3, goal=goal,
                  spawn_traffic=False)
    env = DriveEnv(config)
    env.reset(seed=0, options={"world": world})
    driver = make_driver("agent", road=road_priors(style))
    driver.reset(SimpleNamespace(config=env.config))
    guidance, odometry, controller = driver.stages.junction, driver.stages.odometry, driver.controller
    finder = driver.stages.exit_line if exit_read else None
    controller.stop_line, controller.stop_line_measured = BAR_AHEAD_M, True
    odometry.road_yaw, odometry.road_offset = 0.0, 0.0
    camera_to_bar = BAR_AHEAD_M + controller.config.camera_to_front_m
    t = np.array([math.cos(entry.travel_heading), math.sin(entry.travel_heading)])
    zebra = next((c for c in town.crosswalks if c.node == entry.node and c.arm == entry.arm), None)
    # the zebra's far edge where our lane crosses it (the detector reads it in the lane's corridor)
    start = town.lane(connector).position(0.0, 0.0)  # our lane's centre at the bar's far edge
    zebra_far = (None if zebra is None else
                 camera_to_bar + ROAD.stop_bar_depth_m + zebra_far_along(zebra, start, entry.travel_heading))
    slope = None
    if zebra is not None and tilt:  # its edges' dz/dx in the approach frame (x right, z ahead)
        axis = np.asarray(zebra.end, float) - np.asarray(zebra.start, float)
        along, across = float(axis @ t), float(axis @ np.array([-t[1], t[0]]))
        slope = along / across if abs(across) > 1e-9 else None
    for _ in range(3):  # the skew is the median of a few readings
        guidance.note(StopLine(camera_to_bar, 0.5, 0.9, 0), zebra_far, town.lane_width, slope,
                      control_kind(entry.control) if kind else None, entry.lane_count if kind else None,
                      entry.lane_count - 1 - k)
    steer, worst, started = 0.0, 0.0, False
    turn_speed = controller.config.junction_turn_speed_mps
    for _ in range(400):
        target = guidance.turn_steer(command, float(world.ego.speed))
        if target is None and started:
            break  # handed over (or out of the turn)
        started = started or target is not None
        rate = controller.config.steer_rate_per_s * driver.dt
        steer = float(np.clip(target if target is not None else 0.0, steer - rate, steer + rate))
        throttle = float(np.clip(0.5 * (turn_speed - world.ego.speed), -1.0, 1.0))
        speed = float(world.ego.speed)  # the speed the step moves the car at (the agent's observation)
        obs, _, terminated, _, _ = env.step(np.array([steer, throttle], np.float32))
        odometry.advance(speed, steer, int(world.command()), driver.dt)
        expected = guidance.exit_expected_rad()
        if finder is not None and expected is not None:
            guidance.note_exit(finder.find(obs["image"], expected, divider=guidance.reads_lane_count))
        outside = world.lane_band_offset_m()
        worst = max(worst, outside if math.isfinite(outside) else OFF_ROAD)
        if terminated:
            break
    env.close()
    return entry.lane_count, town.lane_count(goal), round(worst, 2)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--style", default="suburb")
    ap.add_argument("--towns", default="4000,4001", help="comma-separated town seeds")
    ap.add_argument("--entries", type=int, default=14, help="the first N junction entries of each town")
    ap.add_argument("--command", choices=("left", "right"), default="right")
    ap.add_argument("--no-tilt", action="store_true", help="leave the zebra's slope out: square junctions assumed")
    ap.add_argument("--no-kind", action="store_true",
                    help="leave out what governs the arm and our road's lanes (the cross street's lane count guessed "
                         "blind)")
    ap.add_argument("--no-exit", action="store_true", help="do not read the road turned into in the turn")
    ap.add_argument("--inner", action="store_true",
                    help="start each turn from the inner lane of a two-lane road (a right turn whose lane change was "
                         "held); roads of one lane are left out")
    args = ap.parse_args()
    command = Command.LEFT if args.command == "left" else Command.RIGHT
    worst = []
    print("| town | entry | our lanes | cross street's | largest outside its lanes (m) |\n|---|---|---|---|---|")
    for seed in (int(s) for s in args.towns.split(",")):
        for i in range(min(args.entries, len(cached_town(TownConfig.of_style(args.style), seed).entries))):
            row = drive_turn(args.style, seed, i, command, tilt=not args.no_tilt, kind=not args.no_kind,
                             exit_read=not args.no_exit, inner=args.inner)
            if row is not None:
                worst.append(row[2])
                print(f"| {seed} | {i} | {row[0]} | {row[1]} | {row[2]:.2f} |", flush=True)
    over = sum(w > 1.0 for w in worst)
    lane = " from the inner lane" if args.inner else ""
    print(f"\n{args.style}, {args.command} turns{lane}: {len(worst)}; more than 1 m outside their lanes: {over}; "
          f"off the road: {sum(w >= OFF_ROAD for w in worst)}")


if __name__ == "__main__":
    main()
