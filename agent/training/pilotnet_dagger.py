"""DAgger for PilotNet (Ross et al. 2011): the learner drives, the autopilot labels what it sees, retrain.

Behavioural cloning only sees the states the expert visits; once the learner drifts, it is somewhere it
was never shown. Each round here lets the current PilotNet steer (the autopilot keeps the speed, so the
episode looks like the driving it will do), records the autopilot's steering for every frame the learner
saw, adds those episodes to the training set and fine-tunes. A safety driver puts the car back on its
lane when it leaves it, as in evaluation. Rounds are recorded as ordinary episodes under
``<run>/dagger/round_N``, so they can be inspected or reused.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from towndrive.agent.autopilot import Autopilot
from towndrive.agent.perception.pilotnet import preprocess, to_tensor
from towndrive.agent.training.pilotnet_data import FrameSet, load_frames, split_by_episode
from towndrive.data.episodes import EpisodeWriter, next_episode_path
from towndrive.envs.drive_env import DriveConfig, DriveEnv
from towndrive.envs.metrics import needs_intervention
from towndrive.sim.render import LIGHTING_PRESETS
from towndrive.sim.world import WorldConfig


def concat(a: FrameSet, b: FrameSet) -> FrameSet:
    offset = len(a.episode_paths)
    return FrameSet(np.concatenate([a.images, b.images]), np.concatenate([a.steer, b.steer]),
                    np.concatenate([a.speed, b.speed]), np.concatenate([a.command, b.command]),
                    np.concatenate([a.episode, b.episode + offset]), a.episode_paths + b.episode_paths)


def learner_steer(model: torch.nn.Module, rgb: np.ndarray, command: int) -> float:
    with torch.no_grad():
        x = to_tensor(preprocess(rgb))
        y = model(x, torch.tensor([command])) if model.conditional else model(x)
    return min(1.0, max(-1.0, float(y[0, 0])))


def collect(model: torch.nn.Module, folder: Path, episodes: int, seed: int, towns: list[int], seconds: float,
            traffic: float = 0.5) -> dict[str, Any]:
    """Let ``model`` steer for ``episodes`` episodes; write frames labelled by the autopilot into ``folder``."""
    base = WorldConfig()
    world = replace(base, npc_count=round(base.npc_count * traffic), pedestrian_count=round(base.pedestrian_count * traffic))
    env = DriveEnv(DriveConfig(world=world, max_time_s=seconds, terminate_on_infraction=False,
                               terminate_on_route_deviation=False))
    expert = Autopilot()
    weathers = sorted(LIGHTING_PRESETS)
    interventions, steps = 0, 0
    model.eval()
    try:
        for k in tqdm(range(episodes), desc=f"DAgger episodes -> {folder.name}", unit="episode"):
            options = {"town_seed": towns[k % len(towns)], "weather": weathers[k % len(weathers)]}
            obs, info = env.reset(seed=seed + k, options=options)
            expert.reset(env)
            writer = EpisodeWriter(next_episode_path(folder), {"seed": seed + k, **options, "driver": "dagger",
                                                               "privileged": False, "dt_s": world.dt_s})
            done = False
            while not done:
                label = np.asarray(expert.act(obs), np.float32)  # what the expert would do here
                writer.append(obs, label, info)
                action = np.array([learner_steer(model, obs["image"], int(obs["command"])), label[1]], np.float32)
                obs, _, terminated, truncated, info = env.step(action)
                steps += 1
                if needs_intervention(info) and env.world is not None and not env.world.route_done:
                    interventions += 1
                    env.world.put_back_on_route()
                    obs = env.observe()  # the next label is the expert's at the place the car was carried to
                done = terminated or truncated
            writer.close()
    finally:
        env.close()
    return {"episodes": episodes, "steps": steps, "interventions": interventions}


def dagger(model: torch.nn.Module, meta: dict[str, Any], frames: FrameSet, args: argparse.Namespace,
           out: Path, fit: Callable[..., Any]) -> tuple[torch.nn.Module, dict[str, Any]]:
    """``args.dagger`` rounds of collect + fine-tune with ``fit`` (the training loop's); returns the best model and
    its metadata."""
    from towndrive.agent.perception.pilotnet import load_model

    train, val = split_by_episode(frames, args.validation, args.seed)
    towns = sorted({int(_attr_town(p)) for p in frames.episode_paths}) or [1]
    history = []
    for r in range(1, args.dagger + 1):
        folder = out / "dagger" / f"round_{r}"
        stats = collect(model, folder, args.dagger_episodes, seed=50_000 + 1000 * r + args.seed, towns=towns,
                        seconds=args.dagger_seconds)
        history.append(stats)
        print(f"DAgger round {r}: {stats['interventions']} safety-driver interventions in {stats['steps']} steps",
              flush=True)
        train = concat(train, load_frames([folder], side_cameras=False))
        epoch0 = args.epochs + (r - 1) * args.dagger_epochs  # the log continues after the base training
        round_args = argparse.Namespace(**{**vars(args), "lr": args.lr * 0.3})
        fit(model, train, val, round_args, out, first_epoch=epoch0, epochs=args.dagger_epochs,
            meta={**meta, "dagger_round": r, "dagger_history": history}, best_val=float("inf"))
        model, meta = load_model(out / "best.pt")
    return model, meta


def _attr_town(path: Path) -> int:
    import h5py

    with h5py.File(path, "r") as f:
        return int(f.attrs.get("town_seed", 1))
