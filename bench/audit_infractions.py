"""The audit of the infraction detectors over many routes: what the world reported against what
``envs.audit`` recomputes from each episode's recorded ground truth, per driver and kind.

  python bench/audit_infractions.py                       # 120 autopilot + 80 light-ignoring autopilot routes
  python bench/audit_infractions.py --gather out/rerun_traffic out/rerun_notraffic   # add finished evaluations

The drivers run with the camera off (they are privileged), with traffic, 120 s per route, over towns
100-119 (development towns) unless told otherwise. ``autopilot-reckless`` is the autopilot with
``ignore_lights=True`` (CARLA's ``ignore_traffic_lights``): it runs red lights and meets cross traffic, so
the red-light and collision checks are exercised, not only their silence. ``--gather`` adds the audits
already stored in evaluation folders (any driver: PilotNet, the agent, RL). Prints one table; writes it
with every disagreement to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from towndrive.agent.drivers import make_driver  # noqa: E402
from towndrive.envs.audit import AUDITED  # noqa: E402
from towndrive.envs.drive_env import DriveConfig  # noqa: E402
from towndrive.envs.evaluation import evaluate  # noqa: E402
from towndrive.sim.render import LIGHTING_PRESETS  # noqa: E402
from towndrive.sim.world import WorldConfig  # noqa: E402

DRIVERS = {"autopilot": {}, "autopilot-reckless": {"ignore_lights": True}}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--routes", nargs=2, type=int, default=[120, 80], metavar=("AUTOPILOT", "RECKLESS"),
                    help="routes for the autopilot and for the light-ignoring autopilot")
    ap.add_argument("--seed", type=int, default=1000)
    ap.add_argument("--town-seed", type=int, default=100)
    ap.add_argument("--towns", type=int, default=20)
    ap.add_argument("--seconds", type=float, default=120.0)
    ap.add_argument("--traffic", type=float, default=1.0)
    ap.add_argument("--gather", nargs="*", type=Path, default=[], help="evaluation folders whose audits to add")
    ap.add_argument("--out", type=Path, default=Path("out/audit"))
    args = ap.parse_args(argv)
    weathers = sorted(LIGHTING_PRESETS)
    base = WorldConfig()
    world = replace(base, npc_count=round(base.npc_count * args.traffic),
                    pedestrian_count=round(base.pedestrian_count * args.traffic))
    config = DriveConfig(world=world, max_time_s=args.seconds, render_camera=False)

    def options(k: int) -> dict:
        return {"town_seed": args.town_seed + k % args.towns, "weather": weathers[k % len(weathers)]}

    runs: dict[str, list[dict]] = {}
    for (name, kwargs), routes in zip(DRIVERS.items(), args.routes, strict=True):
        if routes <= 0:
            continue
        t0 = time.perf_counter()
        metrics = evaluate(make_driver("autopilot", **kwargs), config, routes, args.seed, args.out / name,
                           video=False, clips=False, plots=False, options=options)
        runs[name] = metrics["episodes"]
        print(f"{name}: {routes} routes in {time.perf_counter() - t0:.0f} s")
    for folder in args.gather:
        for path in sorted(folder.glob("*/metrics.json")) + sorted(folder.glob("metrics.json")):
            metrics = json.loads(path.read_text())
            runs[f"{metrics['driver']} ({path.parent})"] = metrics["episodes"]
    rows, disagreements = [], []
    totals = {kind: [0, 0, 0] for kind in AUDITED}
    for name, episodes in runs.items():
        audited = [e for e in episodes if "audit" in e]
        counts = {kind: [0, 0, 0] for kind in AUDITED}
        for e in audited:
            for kind in AUDITED:
                a = e["audit"][kind]
                counts[kind][0] += a["confirmed"]
                counts[kind][1] += len(a["unconfirmed"])
                counts[kind][2] += len(a["missed"])
                for side in ("unconfirmed", "missed"):
                    disagreements += [{"driver": name, "seed": e["seed"], "town_seed": e.get("town_seed"),
                                       "kind": kind, "side": side, **ev} for ev in a[side]]
        for kind in AUDITED:
            totals[kind] = [t + c for t, c in zip(totals[kind], counts[kind], strict=True)]
        cells = " | ".join("{} / {} / {}".format(*counts[kind]) for kind in AUDITED)
        rows.append(f"| {name} | {len(audited)} | {cells} |")
    cells = " | ".join("**{} / {} / {}**".format(*totals[kind]) for kind in AUDITED)
    n = sum(len([e for e in eps if "audit" in e]) for eps in runs.values())
    head = ["Each cell: confirmed / reported but not confirmed / missed.", "",
            "| driver | routes | " + " | ".join(AUDITED) + " |", "|" + "---|" * (len(AUDITED) + 2)]
    table = "\n".join(head + rows + [f"| **all** | {n} | {cells} |"]) + "\n"
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "table.md").write_text(table)
    (args.out / "disagreements.json").write_text(json.dumps(disagreements, indent=2))
    print(table)
    print(f"{len(disagreements)} disagreements; listed in {args.out / 'disagreements.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
