"""Train a stable-baselines3 RL baseline (PPO or SAC) on Drive-v0.

  python train.py rl --algo ppo --steps 300000 --seed 0           # state observation (privileged), CPU
  python train.py rl --algo sac --observation camera --steps ...   # camera variant, a small CNN (slow)

The state variant observes ``agent.rl_features`` (the autopilot's plan as 24 numbers) with the camera off,
so thousands of steps per second are possible. The reward is Drive-v0's documented one plus a speed limit and
red lights that end the episode (``agent.training.rl_shaping`` says why; ``--no-shaping`` drops them). The run
folder (``--out``) gets SB3's CSV log (``progress.csv``), evaluation logs (``evaluations.npz``), periodic
checkpoints, ``best_model.zip`` (best mean evaluation reward) and ``learning_curve.png``. The final model is
copied to ``--model`` (default ``data/models/rl_<algo>.zip``) together with a JSON of how it was made.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from towndrive.agent.training.devices import add_device_argument  # noqa: E402
from towndrive.agent.training.outputs import add_replace_shipped, replace_shipped  # noqa: E402


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--algo", choices=["ppo", "sac"], default="ppo", help="stable-baselines3 algorithm")
    p.add_argument("--observation", choices=["state", "camera"], default="state", help="policy input: state features or camera")
    p.add_argument("--steps", type=int, default=300_000, help="environment steps in total")
    p.add_argument("--envs", type=int, default=4,
                   help="parallel environments: one process each (SB3's SubprocVecEnv) when more than 1")
    add_device_argument(p, default="cpu", more="The default is cpu: the policy's small MLP is fastest there")
    p.add_argument("--seed", type=int, default=0, help="seed of the environments and the policy")
    p.add_argument("--town-seed", type=int, default=1, help="first training town (towns cycle over --towns)")
    p.add_argument("--towns", type=int, default=8, help="number of training towns (from --town-seed on)")
    p.add_argument("--traffic", type=float, default=0.5, help="NPC and pedestrian density while training")
    p.add_argument("--episode-seconds", type=float, default=60.0, help="length of each training episode")
    p.add_argument("--init", type=Path, default=None,
                   help="start from this saved policy (same algorithm), e.g. a plain-reward run to fine-tune with shaping")
    p.add_argument("--no-shaping", action="store_true",
                   help="train on Drive-v0's plain reward (default: speed limit and red lights added, agent.training.rl_shaping)")
    p.add_argument("--eval-every", type=int, default=20_000, help="evaluate every this many steps")
    p.add_argument("--out", type=Path, default=None, help="run folder (default out/rl_<algo>)")
    p.add_argument("--model", type=Path, default=None, help="final model (default rl_<algo>.zip in the run folder)")
    add_replace_shipped(p, "RL policy (rl_<algo>.zip)")


def make_env(args: argparse.Namespace, rank: int, evaluation: bool = False):
    """A function that builds one monitored environment (SB3's vector envs call it)."""

    def build():
        import gymnasium as gym
        from stable_baselines3.common.monitor import Monitor

        from towndrive.agent.rl_features import StateObservation
        from towndrive.agent.training.rl_shaping import TrafficRulesShaping
        from towndrive.envs.drive_env import DriveConfig, DriveEnv
        from towndrive.sim.render import CameraConfig
        from towndrive.sim.world import WorldConfig

        base = WorldConfig()
        world = replace(base, npc_count=round(base.npc_count * args.traffic),
                        pedestrian_count=round(base.pedestrian_count * args.traffic))
        camera_on = args.observation == "camera"
        config = DriveConfig(world=world, render_camera=camera_on, max_time_s=args.episode_seconds,
                             camera=CameraConfig(width=128, height=64) if camera_on else CameraConfig())
        env: gym.Env = DriveEnv(config)
        if not args.no_shaping:
            env = TrafficRulesShaping(env)
        env = _TownPerEpisode(env, args.town_seed, args.towns, offset=rank + (1000 if evaluation else 0))
        env = StateObservation(env) if not camera_on else _CameraObservation(env)
        return Monitor(env)

    return build


class _TownPerEpisode:
    """Wrapper (duck-typed gym.Wrapper) that cycles training towns per reset."""

    def __new__(cls, env, first_town: int, towns: int, offset: int):
        import gymnasium as gym

        class TownPerEpisode(gym.Wrapper):
            def __init__(self, inner):
                super().__init__(inner)
                self.k = offset

            def reset(self, **kwargs):
                options = dict(kwargs.pop("options", None) or {})
                options.setdefault("town_seed", first_town + self.k % towns)
                self.k += 1
                return self.env.reset(options=options, **kwargs)

        return TownPerEpisode(env)


class _CameraObservation:
    """The camera variant: the 128x64 frame (channels first for SB3's CNN) plus speed and command."""

    def __new__(cls, env):
        import gymnasium as gym

        class CameraObservation(gym.ObservationWrapper):
            def __init__(self, inner):
                super().__init__(inner)
                h, w = inner.observation_space["image"].shape[:2]
                self.observation_space = gym.spaces.Dict({
                    "image": gym.spaces.Box(0, 255, (3, h, w), np.uint8),
                    "state": gym.spaces.Box(-5.0, 5.0, (5,), np.float32)})

            def observation(self, obs):
                state = np.zeros(5, np.float32)
                state[0] = float(obs["speed"][0]) / 10.0
                state[1 + int(obs["command"])] = 1.0
                return {"image": np.ascontiguousarray(obs["image"].transpose(2, 0, 1)), "state": state}

        return CameraObservation(env)


def plot_learning_curve(out: Path) -> Path:
    import csv

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 3.8))
    progress = out / "progress.csv"
    if progress.exists():
        with progress.open() as fh:
            rows = [r for r in csv.DictReader(fh) if r.get("rollout/ep_rew_mean")]
        if rows:
            ax.plot([int(r["time/total_timesteps"]) for r in rows], [float(r["rollout/ep_rew_mean"]) for r in rows],
                    label="training episodes (mean reward)")
    evals = out / "evaluations.npz"
    if evals.exists():
        data = np.load(evals)
        ax.errorbar(data["timesteps"], data["results"].mean(axis=1), yerr=data["results"].std(axis=1), fmt="o-",
                    label="evaluation (held-out reset seeds)")
    ax.set_xlabel("environment steps")
    ax.set_ylabel("episode reward")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    path = out / "learning_curve.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def run(args: argparse.Namespace) -> int:
    import torch
    from stable_baselines3 import PPO, SAC
    from stable_baselines3.common.logger import configure
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    from towndrive.agent.training.devices import resolve_device

    out = args.out or Path(f"out/rl_{args.algo}")
    model_path = args.model or out / f"rl_{args.algo}.zip"
    out.mkdir(parents=True, exist_ok=True)
    try:
        device = str(resolve_device(args.device))
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    torch.set_num_threads(1)
    builders = [make_env(args, k) for k in range(args.envs)]
    # one process per environment when there are several (forkserver: no forked torch or pygame state)
    venv = SubprocVecEnv(builders, start_method=_start_method()) if args.envs > 1 else DummyVecEnv(builders)
    venv.seed(args.seed)
    eval_env = DummyVecEnv([make_env(args, 0, evaluation=True)])
    eval_env.seed(args.seed + 10_000)
    policy = "MlpPolicy" if args.observation == "state" else "MultiInputPolicy"
    if args.init is not None and not args.init.is_file():
        raise SystemExit(f"--init: no saved policy at {args.init}")
    if args.algo == "ppo":
        model = PPO(policy, venv, seed=args.seed, n_steps=512, batch_size=256, learning_rate=3e-4, gamma=0.99,
                    ent_coef=0.0, verbose=0, device=device)
    else:
        model = SAC(policy, venv, seed=args.seed, buffer_size=200_000, learning_starts=5_000, batch_size=256,
                    verbose=0, device=device)
    if args.init is not None:  # weights and optimiser state only: never the pickled objects of SB3's load()
        model.set_parameters(str(args.init), exact_match=True, device=device)
    model.set_logger(configure(str(out), ["csv"]))
    try:
        return _learn(model, args, venv, eval_env, out, model_path)
    finally:
        venv.close()
        eval_env.close()


def _start_method() -> str:
    import multiprocessing

    return "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"


def _learn(model, args: argparse.Namespace, venv, eval_env, out: Path, model_path: Path) -> int:
    import warnings

    from stable_baselines3.common.callbacks import CheckpointCallback, EvalCallback

    # evaluation runs in this process (a DummyVecEnv) while training may use subprocesses: that is intended
    warnings.filterwarnings("ignore", message="Training and eval env are not of the same type")
    callbacks = [
        EvalCallback(eval_env, n_eval_episodes=4, eval_freq=max(1, args.eval_every // args.envs), log_path=str(out),
                     best_model_save_path=str(out), deterministic=True, verbose=0),
        CheckpointCallback(save_freq=max(1, 50_000 // args.envs), save_path=str(out / "checkpoints"), name_prefix="rl"),
    ]
    t0 = time.perf_counter()
    model.learn(total_timesteps=args.steps, callback=callbacks, progress_bar=True)
    wall = time.perf_counter() - t0
    model.save(out / "final_model.zip")
    best = out / "best_model.zip"
    model_path.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(best if best.exists() else out / "final_model.zip", model_path)
    curve = plot_learning_curve(out)
    record = {"algo": args.algo, "observation": args.observation, "steps": args.steps, "envs": args.envs,
              "device": str(model.device),
              "seed": args.seed, "towns": [args.town_seed, args.town_seed + args.towns - 1], "traffic": args.traffic,
              "shaping": not args.no_shaping, "init": str(args.init) if args.init else None,
              "command": "python train.py " + " ".join(sys.argv[1:]),
              "wall_s": round(wall, 1),
              "steps_per_s": round(args.steps / wall, 1), "learning_curve": str(curve)}
    model_path.with_suffix(".json").write_text(json.dumps(record, indent=2))
    print(json.dumps(record, indent=2))
    if args.replace_shipped:
        replace_shipped([model_path, model_path.with_suffix(".json")], [f"rl_{args.algo}.zip", f"rl_{args.algo}.json"])
    print(f"Model: {model_path}; run folder: {out}")
    return 0
