"""Fingerprint of seeded closed-loop runs: a hash of every frame, action and reason, per route.

Why: a refactor of a driver must not change what it does. Two builds of the code that print the same
fingerprints drove the same routes through the same frames with the same actions, bit for bit; the route
figures of ``compare_drivers.py`` then agree too. Run it before a change and after, and compare:

  python bench/agent_fingerprint.py --out out/fingerprint_before.json
  python bench/agent_fingerprint.py --compare out/fingerprint_before.json

Routes are those of ``compare_drivers.py`` (town ``town_seed + k % towns``, the weathers in turn, traffic x1),
each cut at ``--until`` seconds. Exits 1 when ``--compare`` finds a route that differs.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from towndrive.agent.drivers import make_driver  # noqa: E402
from towndrive.envs.drive_env import DriveConfig, DriveEnv  # noqa: E402
from towndrive.envs.evaluation import run_episode  # noqa: E402
from towndrive.envs.metrics import episode_metrics  # noqa: E402
from towndrive.sim.render import LIGHTING_PRESETS  # noqa: E402
from towndrive.sim.world import WorldConfig  # noqa: E402


class HashingDriver:
    """Forwards to a driver and hashes what it saw and did."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self.name, self.privileged = inner.name, inner.privileged
        self.digest = hashlib.sha256()
        self.steps = 0

    def reset(self, *args: Any) -> None:
        self.inner.reset(*args)

    def act(self, observation: dict[str, Any]) -> np.ndarray:
        action = np.asarray(self.inner.act(observation), np.float32)
        self.digest.update(np.ascontiguousarray(observation["image"]).tobytes())
        self.digest.update(action.tobytes())
        self.digest.update(getattr(self.inner, "reason", "").encode())
        self.steps += 1
        return action

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--driver", default="agent")
    ap.add_argument("--routes", type=int, default=4)
    ap.add_argument("--seed", type=int, default=500)
    ap.add_argument("--town-seed", type=int, default=100)
    ap.add_argument("--towns", type=int, default=5)
    ap.add_argument("--until", type=float, default=40.0, help="seconds driven per route")
    ap.add_argument("--out", type=Path, help="write the fingerprints here (JSON)")
    ap.add_argument("--compare", type=Path, help="compare with fingerprints written earlier")
    args = ap.parse_args(argv)
    weathers = sorted(LIGHTING_PRESETS)
    config = DriveConfig(world=WorldConfig(), max_time_s=args.until, terminate_on_infraction=False,
                         terminate_on_route_deviation=False)
    env = DriveEnv(config)
    driver = HashingDriver(make_driver(args.driver))
    prints: dict[str, dict[str, Any]] = {}
    try:
        for k in range(args.routes):
            seed = args.seed + k
            options = {"town_seed": args.town_seed + k % args.towns, "weather": weathers[k % len(weathers)]}
            driver.digest, driver.steps = hashlib.sha256(), 0
            trace = run_episode(env, driver, seed, options=options, until_s=args.until)
            m = episode_metrics(trace)
            prints[str(seed)] = {"hash": driver.digest.hexdigest(), "steps": driver.steps,
                                 "driving_score": m["driving_score"], "route_completion": m["route_completion"]}
            print(f"route {seed} ({options['town_seed']}, {options['weather']}): {driver.steps} steps, "
                  f"{driver.digest.hexdigest()[:16]}, score {m['driving_score']}", flush=True)
    finally:
        env.close()
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(prints, indent=1) + "\n")
    if args.compare:
        before = json.loads(args.compare.read_text())
        differ = [s for s in prints if before.get(s) != prints[s]]
        print(f"{len(prints) - len(differ)} of {len(prints)} routes identical to {args.compare}"
              + (f"; differ: {', '.join(differ)}" if differ else ""))
        return 1 if differ else 0
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
