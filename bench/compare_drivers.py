"""Closed-loop comparison of drivers on the same seeded routes: one table, one row per driver.

Each driver runs ``envs.evaluation.evaluate`` on the same episodes (seed, town and weather per episode),
with the safety driver of ``envs.metrics``. The defaults are the PilotNet issue's held-out test: towns
100-104 (never used for training), every weather preset, no traffic.

  python bench/compare_drivers.py --drivers autopilot pilotnet --episodes 10 --traffic 0
  python bench/compare_drivers.py --drivers autopilot pilotnet --traffic 1 --out out/compare_traffic
  python bench/compare_drivers.py --drivers autopilot agent --workers auto     # one worker process per core

Per-driver reports (metrics.json, table.md, plots, the first episode's video) go to ``--out/<driver>``,
the comparison to ``--out/table.md``.
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from towndrive.agent.drivers import make_driver  # noqa: E402
from towndrive.drive_cli import add_agent_variant_arguments, agent_variant  # noqa: E402
from towndrive.envs.drive_env import DriveConfig  # noqa: E402
from towndrive.envs.evaluation import evaluate  # noqa: E402
from towndrive.envs.parallel import DriverSpec, available_cores, parse_workers  # noqa: E402
from towndrive.envs.rules_cli import add_rule_arguments, rules_from_arguments  # noqa: E402
from towndrive.extras import import_for  # noqa: E402
from towndrive.sim.render import LIGHTING_PRESETS  # noqa: E402
from towndrive.sim.splits import TOWN_SPLITS, split_towns  # noqa: E402
from towndrive.sim.town import TownConfig  # noqa: E402
from towndrive.sim.town_style import STYLES  # noqa: E402
from towndrive.sim.world import WorldConfig  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--drivers", nargs="+", default=["autopilot", "pilotnet"],
                    help="driver names; NAME@MODEL uses another model file (e.g. pilotnet@out/pilotnet/bc.pt)")
    ap.add_argument("--episodes", type=int, default=10)
    ap.add_argument("--seed", type=int, default=500)
    ap.add_argument("--town-seed", type=int, default=None,
                    help="first town (default 100, or the split's first; with --split, a town inside it)")
    ap.add_argument("--towns", type=int, default=5)
    ap.add_argument("--town-style", default="classic", choices=sorted(STYLES), help="the kind of town")
    ap.add_argument("--split", default=None, choices=list(TOWN_SPLITS),
                    help="take the towns from this split's town seeds (sim/splits.py)")
    ap.add_argument("--weathers", default="all", help="comma-separated presets or 'all'")
    ap.add_argument("--traffic", type=float, default=0.0, help="NPC and pedestrian density (0: empty town)")
    ap.add_argument("--seconds", type=float, default=120.0, help="time limit per episode")
    ap.add_argument("--video", action="store_true", help="also write each driver's first-episode video")
    ap.add_argument("--no-clips", action="store_true",
                    help="no clip around each infraction and take-over (they draw the map every step: about 1 ms)")
    ap.add_argument("--workers", default="1", metavar="N",
                    help="run each driver's episodes on N worker processes ('auto': one per available core); "
                         "the figures are the serial run's")
    ap.add_argument("--ray", nargs="?", const="local", default=None, metavar="ADDRESS",
                    help="run the episodes as Ray tasks: a local cluster of --workers CPUs, or the cluster at ADDRESS "
                         "(needs towndrive[cluster])")
    ap.add_argument("--out", type=Path, default=Path("out/compare"))
    ap.add_argument("--pipeline", action="store_true",
                    help="the agent pipelined: it perceives frame t while the simulator renders frame t+1 and acts a "
                         "frame late (AgentConfig.pipeline); its row is 'agent (pipelined)'")
    add_rule_arguments(ap)
    add_agent_variant_arguments(ap)
    ap.add_argument("--camera-raise-m", type=float, default=0.0,
                    help="mount the camera this much higher than the default rig (a different car)")
    ap.add_argument("--hfov-deg", type=float, default=None, help="the camera's horizontal field of view")
    ap.add_argument("--reuse", action="store_true",
                    help="take a driver's row from an earlier run in --out with the same settings instead of re-running")
    args = ap.parse_args(argv)
    if args.split is not None:
        try:
            args.town_seed = split_towns(args.split, args.towns, args.town_seed)[0]
        except ValueError as err:
            ap.error(str(err))
    elif args.town_seed is None:
        args.town_seed = 100
    args.workers = parse_workers(args.workers)
    if args.ray:
        import_for("ray", "--ray")
        if args.ray == "local" and args.workers == 1:
            args.workers = available_cores()
    weathers = sorted(LIGHTING_PRESETS) if args.weathers == "all" else args.weathers.split(",")
    base = WorldConfig(town=TownConfig.of_style(args.town_style))
    world = replace(base, npc_count=round(base.npc_count * args.traffic),
                    pedestrian_count=round(base.pedestrian_count * args.traffic))
    rig = DriveConfig().camera
    camera = replace(rig, mount_height_m=rig.mount_height_m + args.camera_raise_m,
                     hfov_deg=rig.hfov_deg if args.hfov_deg is None else args.hfov_deg)
    config = DriveConfig(world=world, max_time_s=args.seconds, camera=camera)
    rules = rules_from_arguments(args)

    options = functools.partial(episode_options, args.town_seed, args.towns, weathers)

    settings = {k: v for k, v in vars(args).items()
                if k not in ("drivers", "out", "reuse", "video", "no_clips", "workers", "ray")}
    rows = []
    for spec in args.drivers:
        name, _, model = spec.partition("@")
        label = f"{name} ({Path(model).stem})" if model else name
        kwargs: dict = {"model": Path(model)} if model else {}
        piped = args.pipeline and name == "agent"
        if name == "agent":
            kwargs.update(agent_variant(args.town_style, args.road_priors, args.signs))
            label += " (six classes)" if args.signs is False else ""
        if name == "agent":
            # One worker process per core: each agent then keeps to its own core (the actions are the same).
            kwargs["stage_threads"] = 1 if args.workers > 1 or args.ray else 0
        if piped:
            kwargs["pipeline"] = True
            label += " (pipelined)"
        t0 = time.perf_counter()
        folder = args.out / ((f"{name}_{Path(model).stem}" if model else name) + ("_pipelined" if piped else ""))
        earlier = folder / "settings.json"
        if args.reuse and earlier.is_file() and json.loads(earlier.read_text()) == settings:
            metrics = json.loads((folder / "metrics.json").read_text())
            print(f"{name}: reusing {folder / 'metrics.json'}")
        else:
            spec = DriverSpec.of(make_driver, name, **kwargs)
            driver = spec.build()
            # A privileged driver never looks at the pictures: without a video, skip rendering them (the
            # world, and so every figure, is the same; it runs about 50 times faster).
            blind = driver.privileged and not args.video
            metrics = evaluate(spec if args.workers > 1 or args.ray else driver,
                               replace(config, render_camera=False) if blind else config, args.episodes,
                               args.seed, folder, video=args.video, options=options, rules=rules,
                               clips=not args.no_clips, workers=args.workers, ray=args.ray)
            earlier.write_text(json.dumps(settings, indent=2))
            (folder / "wall_s.txt").write_text(f"{time.perf_counter() - t0:.1f}\n")
        m = metrics["mean"]
        inf = ", ".join(f"{k} {v}" for k, v in sorted(m["infractions"].items())) or "none"
        rows.append(f"| {label} | {m['route_completion']:.1f} | {m['driving_score']:.1f} | {m['autonomy']:.2f} | "
                    f"{m['interventions']} | {m['mean_abs_lane_offset_m']:.3f} | {m['mean_speed_mps']:.2f} | "
                    f"{m['distance_km']:.2f} | {inf} | {m.get('standing_clear_s', 0.0):.0f} / "
                    f"{m.get('longest_clear_hold_s', 0.0):.0f} | {_audit_cell(m)} | "
                    f"{float((folder / 'wall_s.txt').read_text()):.0f} |")
    style = "" if args.town_style == "classic" else f"{args.town_style} "
    towns = f"{args.town_seed}-{args.town_seed + args.towns - 1}"
    head = [f"{style}Towns {towns}, seeds {args.seed}-{args.seed + args.episodes - 1}, "
            f"weathers {', '.join(weathers)}, traffic x{args.traffic:g}, {args.seconds:g} s per episode", "",
            "| driver | route completion % | driving score | autonomy % | interventions | mean abs lane offset m "
            "| mean speed m/s | km | infractions | standing clear s: total / longest | audit: confirmed / "
            "unconfirmed / missed | wall s |", "|" + "---|" * 12]
    table = "\n".join(head + rows) + "\n"
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "table.md").write_text(table)
    print(table)
    return 0


def episode_options(town_seed: int, towns: int, weathers: list[str], k: int) -> dict:
    """Town and weather of the k-th episode."""
    return {"town_seed": town_seed + k % towns, "weather": weathers[k % len(weathers)]}


def _audit_cell(mean: dict) -> str:
    """The audit of the infraction detectors over the driver's episodes, summed over kinds."""
    audit = mean.get("audit")
    if not audit:
        return "-"
    return " / ".join(str(sum(c[k] for c in audit.values())) for k in ("confirmed", "unconfirmed", "missed"))


if __name__ == "__main__":
    sys.exit(main())
