"""Where a route's time goes: the agent against the autopilot on the same route, stretch by stretch.

Why: on the styled towns' routes the agent's score loses mostly on time (route completion at the time limit), and
an episode's mean speed does not say where. Both drivers drive the same seeded route (same town, weather and
traffic); for every stretch of ``--every`` metres along the route this prints the time each took and the agent's
three most frequent reasons there (``AgentDriver.reason``). A wait the autopilot did not have at a light is a
light reached later; a turn taken slower shows as a longer stretch with "turning at a junction".

  python bench/route_time.py --town-style downtown --town-seed 4002 --seed 507 --weather overcast \
      --road-priors style
"""

from __future__ import annotations

import argparse
import re
import sys
from collections import Counter
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from towndrive.agent.drivers import make_driver  # noqa: E402
from towndrive.drive_cli import add_agent_variant_arguments, agent_variant  # noqa: E402
from towndrive.envs import options  # noqa: E402
from towndrive.envs.drive_env import DriveConfig, DriveEnv  # noqa: E402
from towndrive.sim.town import TownConfig  # noqa: E402
from towndrive.sim.world import WorldConfig  # noqa: E402

Row = tuple[float, float, str]  # time (s), route progress (m), the driver's reason


def drive(driver_name: str, args: argparse.Namespace) -> list[Row]:
    """One episode of ``driver_name`` on the route; a row per step."""
    world = WorldConfig(town=TownConfig.of_style(args.town_style))
    config = replace(DriveConfig(world=world, max_time_s=args.seconds), terminate_on_infraction=False,
                     terminate_on_route_deviation=False)
    kwargs = agent_variant(args.town_style, args.road_priors, args.signs) if driver_name == "agent" else {}
    driver = make_driver(driver_name, **kwargs)
    env = DriveEnv(config)
    try:
        obs, _ = env.reset(seed=args.seed, options={"town_seed": args.town_seed, "weather": args.weather,
                                                    "traffic_density": args.traffic})
        driver.reset(env)
        rows: list[Row] = []
        t, done = 0.0, False
        while not done:
            action = driver.act(obs)
            obs, _, terminated, truncated, _ = env.step(np.asarray(action, np.float32))
            t += env.world.config.dt_s
            done = terminated or truncated
            reason = re.sub(r"[#\d.]+", "N", str(getattr(driver, "reason", "")).split(";")[0])
            rows.append((t, env.world.route_progress_m, reason))
        return rows
    finally:
        env.close()


def reached(rows: list[Row], metres: float) -> float | None:
    """When the route's ``metres`` mark was first reached, None if never."""
    return next((t for t, s, _ in rows if s >= metres), None)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--town-style", default="downtown")
    ap.add_argument("--town-seed", type=int, default=4002)
    ap.add_argument("--seed", type=int, default=507)
    ap.add_argument("--weather", default="overcast")
    ap.add_argument("--traffic", type=float, default=1.0, help="NPC and pedestrian density (1: the evaluations')")
    ap.add_argument("--seconds", type=float, default=120.0)
    ap.add_argument("--every", type=float, default=25.0, help="stretch length along the route (m)")
    add_agent_variant_arguments(ap)
    args = ap.parse_args()
    if args.every <= 0:
        ap.error(f"--every must be a positive number of metres, not {args.every}.")
    options.traffic_density(args.traffic, "--traffic")
    options.episode_seconds(args.seconds, "--seconds")
    autopilot, agent = drive("autopilot", args), drive("agent", args)
    print(f"route progress at the end: autopilot {autopilot[-1][1]:.0f} m in {autopilot[-1][0]:.1f} s, "
          f"agent {agent[-1][1]:.0f} m in {agent[-1][0]:.1f} s\n")
    print("| stretch (m) | autopilot s | agent s | the agent's reasons there (s) |")
    print("|---|---|---|---|")
    before_ap, before_ag, start = 0.0, 0.0, 0.0
    dt = agent[1][0] - agent[0][0] if len(agent) > 1 else 0.05
    for end in np.arange(args.every, agent[-1][1] + args.every, args.every):
        t_ag = reached(agent, float(end))
        if t_ag is None:
            break
        t_ap = reached(autopilot, float(end))
        why = Counter(r for t, _, r in agent if before_ag < t <= t_ag)
        reasons = ", ".join(f"{r} {n * dt:.1f}" for r, n in why.most_common(3))
        ap_s = "-" if t_ap is None else f"{t_ap - before_ap:.1f}"
        print(f"| {start:.0f}-{end:.0f} | {ap_s} | {t_ag - before_ag:.1f} | {reasons} |")
        before_ap, before_ag, start = (t_ap if t_ap is not None else before_ap), t_ag, float(end)


if __name__ == "__main__":
    main()
