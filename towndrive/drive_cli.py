"""Run a driver in the simulator: a demo drive, recording, closed-loop evaluation, or scenarios.

  python drive.py                                         # the agent (shipped models) drives: video, frames, summary
  python drive.py --driver autopilot --record data/episodes --episodes 5 [--noise]
  python drive.py --driver keyboard --record data/mine --episodes 3     # a window; arrows/WASD, P, R, Esc
  python drive.py --driver autopilot --evaluate --episodes 20 --seed 100 --out out/eval
  python drive.py --driver autopilot --scenario all
  python drive.py --driver pilotnet --evaluate --episodes 10 --seed 500 --town-seed 100 --towns 5 --traffic 0

Recording writes one HDF5 file per finished episode (see data/episodes.py); Ctrl-C keeps every
finished episode and drops only the one in progress. Summarise or convert datasets with
``python -m data summary DIR`` and ``python -m data import-udacity|export-udacity SRC DST``.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import signal
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from towndrive.agent.drivers import BUILTIN
from towndrive.cli import HelpFormatter
from towndrive.envs.rules_cli import add_rule_arguments, rules_from_arguments
from towndrive.extras import MissingExtra
from towndrive.sim.spec import EPISODE_S, WEATHERS
from towndrive.sim.splits import TOWN_SPLITS, split_towns
from towndrive.sim.town_style import STYLES


def parse_args(argv: list[str] | None = None, prog: str | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog=prog, description=__doc__, formatter_class=HelpFormatter)
    p.add_argument("--driver", default="agent", choices=sorted(BUILTIN),
                   help="who drives: agent (default; shipped models, camera only), autopilot (privileged expert), "
                        "keyboard, gamepad, pilotnet, rl (privileged)")
    p.add_argument("--model", type=Path, default=None,
                   help="pilotnet/agent/rl: model file (default data/models/pilotnet.pt, data/models/rl_ppo.zip)")
    p.add_argument("--backend", default=None, choices=["onnxruntime", "torch"],
                   help="pilotnet/agent: PilotNet's inference backend, named as in the profiles (default: torch for a "
                        "--model .pt, else onnxruntime)")
    p.add_argument("--target-speed", type=float, default=None, help="pilotnet: cruise speed in m/s (default 7)")
    p.add_argument("--threads", type=int, default=None, choices=(0, 1, 2),
                   help="agent: threads for a frame's independent stages: 1 one after another, 2 on two cores, 0 the "
                        "faster of the two, timed now and then (default; 1 with --workers or --ray: one core per "
                        "worker); the actions are the same")
    add_agent_variant_arguments(p)
    p.add_argument("--pipeline", action="store_true",
                   help="agent: perceive frame t while the simulator renders frame t+1, acting a frame late")
    p.add_argument("--profile", default=None, metavar="NAME",
                   help="run the agent with a deployment profile (agent/deploy/profiles/NAME.yaml, or a .yaml path): its "
                        "backends, module rates, budgets, camera and alerts; a real camera runs without the simulator")
    p.add_argument("--camera", default=None, metavar="SOURCE",
                   help="with --profile: real frames instead of the profile's camera: a video file, an episode .h5, "
                        "usb:N or csi:N")
    p.add_argument("--speed", type=float, default=8.0, help="real frames: own speed (m/s) when the source has none")
    p.add_argument("--show", action="store_true", help="real frames: show the overlay in a window")
    p.add_argument("--alerts", default=None, metavar="PATH", help="with --profile: decisions as JSON lines ('-': stdout)")
    p.add_argument("--serial", default=None, metavar="PORT", help="with --profile: the alert line protocol to PORT")
    p.add_argument("--seed", type=int, default=0, help="first episode seed (traffic, start and route)")
    p.add_argument("--town-seed", type=int, default=None,
                   help="which town to generate (default 0, or the first town of --split; with --split, a town inside it)")
    p.add_argument("--town-style", default="classic", choices=sorted(STYLES),
                   help="the kind of town (sim/town_style.py): classic (the original grid of arterials and signals), "
                        "downtown or suburb")
    p.add_argument("--split", default=None, choices=list(TOWN_SPLITS),
                   help="record/evaluate: take the towns from this split's town seeds (docs/environment.md)")
    p.add_argument("--weather", default="noon", choices=WEATHERS, help="lighting preset")
    p.add_argument("--towns", type=int, default=1,
                   help="record/evaluate: cycle episodes through this many towns, from --town-seed up")
    p.add_argument("--weathers", type=_weather_list, default=None, metavar="A,B,..",
                   help="record/evaluate: cycle episodes through these presets ('all' for every one)")
    p.add_argument("--traffic", type=float, default=1.0, help="traffic density multiplier (NPCs and pedestrians)")
    p.add_argument("--seconds", type=float, default=None,
                   help="longest episode, simulated seconds (default 60 for a demo drive or a recording, 180 to evaluate)")
    p.add_argument("--width", type=int, default=320, help="camera width in pixels")
    p.add_argument("--height", type=int, default=160, help="camera height in pixels")
    p.add_argument("--out", type=Path, default=None, help="output folder (default out/drive, out/eval, out/scenarios)")
    p.add_argument("--frames", type=int, default=4, help="demo: how many camera frames to save as PNG")
    p.add_argument("--no-video", action="store_true", help="skip the MP4")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--record", type=Path, metavar="DIR", help="record episodes into DIR (appends)")
    mode.add_argument("--evaluate", action="store_true", help="closed-loop evaluation with CARLA-style metrics")
    mode.add_argument("--scenario", metavar="NAME", help="run a scenario of the suite, or 'all'")
    p.add_argument("--episodes", type=int, default=1, help="record/evaluate: how many episodes")
    p.add_argument("--workers", default="1", metavar="N",
                   help="record/evaluate/scenario all: run episodes on N worker processes, one simulator and one "
                        "driver each ('auto': one per available core); the results are the serial run's")
    p.add_argument("--ray", nargs="?", const="local", default=None, metavar="ADDRESS",
                   help="record/evaluate/scenario all: run the episodes as Ray tasks, on a local Ray cluster of "
                        "--workers CPUs (default: every available core), or on the cluster at ADDRESS ('auto', "
                        "'ray://host:10001'; one task per CPU unless --workers says otherwise). Needs towndrive[cluster]; "
                        "on several machines, --out must be on a file system every node sees (recorded episodes "
                        "come back to the recording folder)")
    p.add_argument("--shared-dir", type=Path, default=None, metavar="DIR",
                   help="record --ray: a folder every Ray node sees at this path; workers write their episodes there "
                        "and each finished one is moved into the recording folder (without it, each comes back "
                        "through Ray's object store)")
    p.add_argument("--until", type=float, default=None, metavar="SECONDS",
                   help="evaluate: stop each episode at this time and save its last frame (replay an event: the "
                        "report gives seed, town and weather)")
    add_rule_arguments(p, prefix="evaluate: ")
    p.add_argument("--noise", action="store_true", help="autopilot: inject steering perturbations (recoveries)")
    p.add_argument("--depth", action="store_true", help="record: also store depth")
    p.add_argument("--segmentation", action="store_true", help="record: also store segmentation")
    p.add_argument("--stereo", action="store_true", help="record: also store the right stereo image")
    p.add_argument("--side-cameras", action="store_true",
                   help="record: also store left and right side cameras (0.6 m off centre) for PilotNet training")
    return p.parse_args(argv)


def add_agent_variant_arguments(p: argparse.ArgumentParser) -> None:
    """The agent's road design and sign detector as flags (here and in ``bench/compare_drivers.py``)."""
    p.add_argument("--road-priors", default="classic", choices=["classic", "style"],
                   help="agent: the road design it assumes, the classic towns' or the --town-style's (measured on "
                        "its training towns, sim.road_priors)")
    p.add_argument("--signs", action=argparse.BooleanOptionalAction, default=None,
                   help="agent: the detector with the road-sign classes and the sign reader (stop, yield, limits; the "
                        "default); --no-signs: the six-class detector of cars, people and lights")


def agent_variant(town_style: str, road_priors_name: str, signs: bool | None) -> dict[str, Any]:
    """The agent's keyword arguments for ``--road-priors`` and ``--signs`` / ``--no-signs`` (None: the agent's
    default detector, the one with the signs)."""
    kwargs: dict[str, Any] = {}
    if road_priors_name == "style":
        from towndrive.sim.road_priors import road_priors

        kwargs["road"] = road_priors(town_style)
    if signs:
        from towndrive.agent.shipped import DETECTOR_SIGNS_ONNX, SIGN_READER_ONNX

        kwargs.update(detector=DETECTOR_SIGNS_ONNX, sign_reader=SIGN_READER_ONNX)
    elif signs is False:
        from towndrive.agent.shipped import DETECTOR_ONNX

        kwargs.update(detector=DETECTOR_ONNX, sign_reader=None)
    return kwargs


def check_args(args: argparse.Namespace) -> None:
    """Every number flag against the range its consumer accepts (the same helpers the env and the camera use),
    so a bad value is one sentence naming the flag before anything runs."""
    from towndrive.envs import options
    from towndrive.sim.checks import check_number
    from towndrive.sim.spec import check_image_size

    check_image_size("--width", args.width)
    check_image_size("--height", args.height)
    options.traffic_density(args.traffic, "--traffic")
    if args.seconds is not None:
        options.episode_seconds(args.seconds, "--seconds")
    check_number("--episodes", args.episodes, 1, None, integer=True)
    check_number("--towns", args.towns, 1, None, integer=True)
    check_number("--frames", args.frames, 0, None, integer=True)
    if args.split is not None:
        if not (args.record or args.evaluate):
            raise ValueError(f"--split {args.split} chooses the towns of a recording or an evaluation; add --record or "
                             "--evaluate (or give a single town with --town-seed).")
        args.town_seed = split_towns(args.split, args.towns, args.town_seed)[0]
    elif args.town_seed is None:
        args.town_seed = 0
    options.town_seed(args.town_seed, "--town-seed")
    options.town_seed(args.town_seed + args.towns - 1, "--town-seed plus --towns - 1")
    options.town_seed(args.seed, "--seed")
    options.town_seed(args.seed + args.episodes - 1, "--seed plus --episodes - 1")
    if args.target_speed is not None:
        check_number("--target-speed", args.target_speed, 0.0, 30.0, lo_open=True)
    check_number("--speed", args.speed, 0.0, 60.0)
    from towndrive.envs.parallel import parse_workers

    args.workers = parse_workers(args.workers)
    if args.workers > 1 and args.driver in ("keyboard", "gamepad"):
        raise ValueError(f"--workers {args.workers}: the {args.driver} driver is one person at one window; drop --workers.")
    if (args.workers > 1 or args.ray) and not (args.record or args.evaluate or args.scenario):
        raise ValueError("--workers and --ray are for record, evaluate and scenario all; a demo drive is one episode.")
    if args.ray:
        if args.driver in ("keyboard", "gamepad"):
            raise ValueError(f"--ray: the {args.driver} driver is one person at one window; drop --ray.")
        from towndrive.envs.parallel import LOCAL_RAY, available_cores
        from towndrive.extras import import_for

        import_for("ray", "--ray")
        if args.ray == LOCAL_RAY and args.workers == 1:
            args.workers = available_cores()
    if args.shared_dir is not None and not (args.ray and args.record):
        raise ValueError(f"--shared-dir {args.shared_dir}: a folder Ray's workers record into; it needs record --ray.")
    if args.until is not None:
        if not args.evaluate:
            raise ValueError(f"--until {args.until} replays an evaluation episode up to a time: it needs --evaluate.")
        check_number("--until", args.until, 0.0, None, lo_open=True)


def _weather_list(text: str) -> list[str]:
    names = list(WEATHERS) if text == "all" else [w.strip() for w in text.split(",") if w.strip()]
    unknown = [w for w in names if w not in WEATHERS]
    if unknown or not names:
        raise argparse.ArgumentTypeError(f"unknown weather {unknown[0] if unknown else text!r}; "
                                         f"choose from {', '.join(WEATHERS)} or 'all'")
    return names


def episode_options(args: argparse.Namespace, k: int) -> dict[str, Any]:
    """Town and weather of the k-th recorded or evaluated episode (``--towns``, ``--weathers``)."""
    weathers = args.weathers or [args.weather]
    return {"town_seed": args.town_seed + k % max(1, args.towns), "weather": weathers[k % len(weathers)]}


def make_config(args: argparse.Namespace) -> Any:
    from dataclasses import replace

    from towndrive.envs.drive_env import DriveConfig
    from towndrive.sim.render import CameraConfig
    from towndrive.sim.town import TownConfig
    from towndrive.sim.world import WorldConfig

    world = WorldConfig(town=TownConfig.of_style(args.town_style))
    if args.traffic != 1.0:
        world = replace(world, npc_count=round(world.npc_count * args.traffic),
                        pedestrian_count=round(world.pedestrian_count * args.traffic))
    seconds = args.seconds if args.seconds is not None else (EPISODE_S if args.evaluate else 60.0)
    return DriveConfig(world=world, camera=CameraConfig(width=args.width, height=args.height),
                       town_seed=args.town_seed, weather=args.weather, max_time_s=seconds,
                       observe_depth=args.depth, observe_segmentation=args.segmentation, observe_stereo=args.stereo,
                       observe_side_cameras=getattr(args, "side_cameras", False))


def make_named_driver(args: argparse.Namespace) -> Any:
    return driver_spec(args).build()


def _profiled_agent(name: str, profile: str) -> Any:
    """The agent as a deployment profile runs it (a module-level factory, so worker processes can build it)."""
    from towndrive.agent.deploy.profiled_agent import ProfiledAgent
    from towndrive.agent.deploy.profiles import load_profile

    return ProfiledAgent(load_profile(profile))


def driver_spec(args: argparse.Namespace) -> Any:
    """The driver the flags ask for, as an ``envs.parallel.DriverSpec``: built here for a serial run, once in
    each worker process for a parallel one. Flag mistakes are raised here, before any worker starts."""
    from towndrive.agent.drivers import make_driver
    from towndrive.envs.parallel import DriverSpec

    if getattr(args, "profile", None):
        if args.driver != "agent":
            raise ValueError(f"--profile runs the agent driver, not {args.driver}; drop --driver.")
        return DriverSpec.of(_profiled_agent, "agent", profile=str(args.profile))

    kwargs: dict[str, Any] = {"noise": True, "noise_seed": args.seed} if args.noise else {}
    if args.noise and args.driver != "autopilot":
        raise ValueError("--noise is for the autopilot only.")
    if args.driver in ("pilotnet", "rl", "agent") and args.model is not None:
        kwargs["model"] = args.model
    if args.driver in ("agent", "pilotnet"):  # the profiles' name for ONNX Runtime is PilotNetModel's "onnx"
        kwargs["backend"] = {"onnxruntime": "onnx"}.get(args.backend, args.backend)
    if args.driver == "pilotnet":
        if args.target_speed is not None:
            kwargs["target_speed_mps"] = args.target_speed
    elif args.target_speed is not None:
        raise ValueError(f"--target-speed is for the pilotnet driver, not {args.driver}.")
    elif args.model is not None and args.driver not in ("rl", "agent"):
        raise ValueError(f"--model is for the pilotnet, agent and rl drivers, not {args.driver}.")
    threads, pipeline = getattr(args, "threads", None), getattr(args, "pipeline", False)
    road, signs = getattr(args, "road_priors", "classic"), getattr(args, "signs", None)
    if args.driver == "agent":
        kwargs.update(agent_variant(args.town_style, road, signs))
    elif road != "classic" or signs is not None:
        raise ValueError(f"--road-priors and --signs / --no-signs are for the agent driver, not {args.driver}.")
    if args.driver == "agent":
        parallel = getattr(args, "workers", 1) > 1 or bool(getattr(args, "ray", None))
        kwargs["stage_threads"] = threads if threads is not None else (1 if parallel else 0)
        if pipeline:
            kwargs["pipeline"] = True
    elif threads is not None or pipeline:
        raise ValueError(f"--threads and --pipeline are for the agent driver, not {args.driver}.")
    return DriverSpec.of(make_driver, args.driver, **kwargs)


# ---------------------------------------------------------------------- modes
def demo(args: argparse.Namespace) -> int:
    import cv2
    from tqdm import tqdm

    from towndrive.envs.drive_env import DriveEnv
    from towndrive.envs.evaluation import video_frame, video_writer

    out = args.out or Path("out/drive")
    config = make_config(args)
    env = DriveEnv(config, render_mode="rgb_array")
    driver = make_named_driver(args)
    out.mkdir(parents=True, exist_ok=True)
    obs, info = env.reset(seed=args.seed)
    driver.reset(env)
    steps = int(config.max_time_s / config.world.dt_s)
    save_at = set(np.linspace(0, steps - 1, args.frames).astype(int).tolist()) if args.frames > 0 else set()
    writer = None if args.no_video else video_writer(out / "video.mp4", env.metadata["render_fps"])
    t0 = time.perf_counter()
    saved, k, terminated = [], 0, False
    infractions: list[dict[str, Any]] = []  # each as the step reported it (the driving score's penalty)
    try:
        for k in tqdm(range(steps), desc="driving", unit="step", mininterval=1.0):
            obs, _, terminated, truncated, info = env.step(driver.act(obs))
            infractions += info["infractions"]
            if writer is not None:
                writer.append_data(video_frame(env, driver, info))
            if k in save_at:
                path = out / f"frame_{k:05d}.png"
                cv2.imwrite(str(path), cv2.cvtColor(obs["image"], cv2.COLOR_RGB2BGR))
                saved.append(path.name)
            if terminated or truncated:
                break
    finally:
        if writer is not None:
            writer.close()
        env.close()
    wall = time.perf_counter() - t0
    from towndrive.envs.metrics import infraction_penalty

    completion = float(info["route"]["completion"])
    counts = info["infraction_counts"]
    if completion >= 0.999:
        limited = "the car completed its route"
    elif terminated:
        limited = (f"the run ended at the first {', '.join(sorted(counts)) or 'infraction'} (a demo run stops there; "
                   "towndrive evaluate lets a safety driver take over instead)")
    else:
        limited = (f"the {config.max_time_s:.0f} s time limit ended the run with {100 * completion:.0f} % of the route "
                   "driven (--seconds sets it)")
    summary = {
        "driver": driver.name, "seed": args.seed, "town_seed": args.town_seed, "weather": args.weather,
        "driving_score": round(100.0 * completion * infraction_penalty(infractions), 2),
        "route_completion_pct": round(100.0 * completion, 2), "infractions": counts, "limited_by": limited,
        "distance_m": round(info["distance_m"], 1), "sim_time_s": info["time_s"], "steps": k + 1,
        "wall_time_s": round(wall, 2), "steps_per_s": round((k + 1) / wall, 1),
        "frames": saved, "video": None if args.no_video else "video.mp4",
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"{driver.name}: driving score {summary['driving_score']:.1f}, route {summary['route_completion_pct']:.1f} %, "
          f"infractions {', '.join(f'{k} {v}' for k, v in sorted(counts.items())) or 'none'}; {limited}.")
    written = (["video.mp4"] if not args.no_video else []) + ([f"{len(saved)} frames"] if saved else []) + ["summary.json"]
    print(f"Outputs in {out}/: {', '.join(written)}.")
    return 0


@dataclass(frozen=True)
class RecordEpisode:
    """One recorded episode as a work item (``envs.parallel``): seed, town and weather, the config and the file it
    becomes. Episode k of a run gets the name the serial run gives it, whichever worker records it."""

    index: int
    seed: int
    options: dict[str, Any]
    config: Any  # DriveConfig
    path: Path
    noise: bool = False
    home: Path | None = None  # where the file belongs when this copy records it elsewhere (a Ray worker's folder)

    def attrs(self, driver: Any, route_total_m: float) -> dict[str, Any]:
        c = self.config
        return {"seed": self.seed, **self.options, "driver": driver.name,
                "side_camera_offset_m": c.side_camera_offset_m if c.observe_side_cameras else 0.0,
                "privileged": driver.privileged, "noise": self.noise, "dt_s": c.world.dt_s,
                "camera": {"width": c.camera.width, "height": c.camera.height, "hfov_deg": c.camera.hfov_deg,
                           "mount_height_m": c.camera.mount_height_m, "pitch_deg": c.camera.pitch_deg},
                "route_total_m": route_total_m}

    def record(self, env: Any, driver: Any, stop: Any = None) -> tuple[Path, int]:
        """Drive the episode into its file (``.partial`` until it finishes, then renamed); its path and frames.
        Anything that stops it (an error, Ctrl-C, a worker's SIGTERM) discards the ``.partial``."""
        from towndrive.data.episodes import EpisodeWriter
        from towndrive.envs.parallel import start_episode

        start_episode(driver, self.index)
        obs, info = env.reset(seed=self.seed, options=self.options)
        driver.reset(env)
        assert env.world is not None
        writer = EpisodeWriter(self.path, self.attrs(driver, env.world.route_total_m))
        try:
            done = False
            while not done:
                action = np.asarray(driver.act(obs), np.float32)
                if stop is not None:
                    stop.check()
                if getattr(driver, "quit_requested", False):
                    raise KeyboardInterrupt
                if getattr(driver, "paused", False):
                    continue
                label = getattr(driver, "clean_action", action)  # noise-free expert label when there is one
                writer.append(obs, label, info)
                obs, _, terminated, truncated, info = env.step(action)
                if hasattr(driver, "update_hud"):
                    driver.update_hud(info, recording=True)
                done = terminated or truncated or getattr(driver, "reset_requested", False)
            steps = writer.steps
            return writer.close({"route_completion": info["route"]["completion"],
                                 "infractions": info["infraction_counts"], "steps_done": writer.steps}), steps
        except BaseException:
            writer.discard()  # first the file, then (the caller) the renderer: nothing half-closed is left for exit
            raise

    def run(self, worker: Any) -> dict[str, Any]:
        _, frames = self.record(worker.env(self.config, render_mode=None), worker.driver)
        return {"path": str(self.home or self.path), "frames": frames}

    def files(self) -> tuple[Path, ...]:
        return (self.path,)

    def writing_into(self, folder: Path) -> RecordEpisode:
        """The same episode recorded into ``folder`` (``envs.parallel.FileItem``: Ray brings the file home)."""
        return replace(self, path=Path(folder) / self.path.name, home=self.home or self.path)

    def failed(self, error: str) -> dict[str, Any]:
        return {"path": None, "frames": 0, "error": error}


def record(args: argparse.Namespace) -> int:
    """Record episodes; each finished one is renamed into place, so Ctrl-C, SIGTERM, SIGHUP or a full disk loses
    only the current one(s), and the run ends with one sentence saying what happened and what was kept."""
    from tqdm import tqdm

    from towndrive.data.episodes import next_episode_path
    from towndrive.data.stopping import Stopped, StopSignals, describe_os_error
    from towndrive.envs.drive_env import DriveEnv

    config = make_config(args)
    if args.workers > 1 or args.ray:
        return _record_parallel(args, config)
    human = args.driver in ("keyboard", "gamepad")
    env = DriveEnv(config)
    driver = make_named_driver(args)
    kept: list[Path] = []
    current: RecordEpisode | None = None
    t0 = time.perf_counter()
    frames = 0
    failure: tuple[str, int] | None = None  # what stopped the recording, and the exit code
    stop = StopSignals().__enter__()
    try:
        for k in tqdm(range(args.episodes), desc="recording", unit="episode", disable=human, mininterval=2.0):
            current = RecordEpisode(k, args.seed + k, episode_options(args, k), config, next_episode_path(args.record),
                                    bool(args.noise))
            path, steps = current.record(env, driver, stop)
            kept.append(path)
            frames += steps
            current = None
    except KeyboardInterrupt:
        failure = ("Interrupted", 130)
    except Stopped as exc:
        failure = (f"Stopped by {exc.name}", exc.exit_code)
    except OSError as exc:
        where = current.path.with_name(current.path.name + ".partial") if current is not None else args.record
        failure = (f"Stopped because {describe_os_error(exc)} writing {where}", 1)
    finally:
        stop.restore()
        env.close()
        if hasattr(driver, "close"):
            driver.close()
    if failure is not None:
        print(f"\n{failure[0]}: kept {len(kept)} finished episode(s) in {args.record}; dropped the one in progress.",
              file=sys.stderr)
        return failure[1]
    wall = time.perf_counter() - t0
    print(f"recorded {len(kept)} episode(s), {frames} frames in {wall:.1f} s ({frames / max(wall, 1e-9):.1f} frames/s) "
          f"into {args.record}")
    for path in kept:
        print(f"  {path}")
    return 0


def _record_parallel(args: argparse.Namespace, config: Any) -> int:
    """``record --workers N``: episode k becomes ``episode_<first + k>.h5`` (the serial run's name) on whichever
    worker records it; each is renamed into place when it finishes."""
    from towndrive.data.episodes import next_episode_path
    from towndrive.data.stopping import StopSignals
    from towndrive.envs.parallel import Interrupted, RunSummary, run_items

    spec = driver_spec(args)
    first = int(next_episode_path(args.record).stem.split("_")[1])
    args.record.mkdir(parents=True, exist_ok=True)
    items = [RecordEpisode(k, args.seed + k, episode_options(args, k), config,
                           args.record / f"episode_{first + k:05d}.h5", bool(args.noise)) for k in range(args.episodes)]
    summary = RunSummary()
    t0 = time.perf_counter()
    with StopSignals() as stop:
        try:
            results = run_items(items, spec, args.workers, f"recording ({args.workers} workers)",
                                lambda: stop.requested, summary, args.ray, shared_dir=args.shared_dir)
        except Interrupted as exc:
            kept = [r for r in exc.results.values() if r["path"]]
            signum = stop.signum or signal.SIGINT
            name = "Interrupted" if signum == signal.SIGINT else f"Stopped by {signal.Signals(signum).name}"
            code = 128 + signum
            print(f"\n{name}: stopped {args.workers} workers; kept {len(kept)} finished episode(s) of {exc.total} in "
                  f"{args.record}; dropped the ones in progress.", file=sys.stderr)
            return code
    kept = [r for r in results if r["path"]]
    frames = sum(r["frames"] for r in results)
    wall = time.perf_counter() - t0
    print(f"recorded {len(kept)} episode(s), {frames} frames in {wall:.1f} s ({frames / max(wall, 1e-9):.1f} frames/s) "
          f"on {args.workers} workers into {args.record}")
    for r in results:
        print(f"  {r['path']}" if r["path"] else f"  failed after a retry: {r['error']}")
    if summary.failed:
        print(f"{len(summary.failed)} episode(s) could not be recorded (each was tried twice); see above.", file=sys.stderr)
        return 1
    return 0


def evaluate(args: argparse.Namespace) -> int:
    from collections import deque

    import cv2
    import imageio.v2 as imageio

    from towndrive.data.stopping import StopSignals
    from towndrive.envs.evaluation import evaluate as run
    from towndrive.envs.parallel import Interrupted

    out = args.out or Path("out/eval")
    config = make_config(args)
    rules = rules_from_arguments(args)
    replay = args.until is not None
    spec = driver_spec(args)
    # With workers, SIGTERM and SIGHUP stop the run as Ctrl-C does (the finished episodes are reported); the serial
    # run keeps Python's own handling.
    parallel = args.workers > 1 or args.ray is not None
    stop = StopSignals() if parallel else contextlib.nullcontext()
    try:
        with stop:
            metrics = run(spec if parallel else spec.build(), config, args.episodes, args.seed, out,
                          video=not args.no_video or replay, options=functools.partial(episode_options, args),
                          rules=rules, until_s=args.until, plots=not replay, workers=args.workers,
                          should_stop=(lambda: stop.requested) if isinstance(stop, StopSignals) else None,
                          ray=args.ray)
    except Interrupted as exc:
        signum = getattr(stop, "signum", None) or signal.SIGINT
        what = "Interrupted" if signum == signal.SIGINT else f"Stopped by {signal.Signals(signum).name}"
        print(f"\n{what}: stopped {args.workers} workers; kept {len(exc.results)} finished episode(s) of "
              f"{exc.total}, reported in {out / 'metrics.json'}.", file=sys.stderr)
        return 128 + signum
    if replay:  # the moment itself, as a picture
        with imageio.get_reader(out / "video.mp4") as reader:
            tail = deque(reader, maxlen=1)
        if tail:
            last = tail[0]
            cv2.imwrite(str(out / f"until_{args.until:.2f}s.png"), cv2.cvtColor(last, cv2.COLOR_RGB2BGR))
            print(f"the last frame, at {args.until:.2f} s: {out / f'until_{args.until:.2f}s.png'}")
    print((out / "table.md").read_text())
    m = metrics["mean"]
    print(f"driving score {m['driving_score']:.2f}, route completion {m['route_completion']:.2f}%, "
          f"autonomy {m['autonomy']:.2f}%, infractions {m['infractions'] or 'none'}; reports in {out}")
    if m.get("failed"):
        print(f"{m['failed']} episode(s) could not be run (each was tried twice) and count as 0; table.md says why.",
              file=sys.stderr)
        return 1
    return 0


def scenario_styles(names: list[str], town_style: str) -> dict[str, list[str]]:
    """The scenarios grouped by the town style each happens in: its place's, else the command line's."""
    from towndrive.envs.scenarios import SCENARIOS

    groups: dict[str, list[str]] = {}
    for name in names:
        place = SCENARIOS[name].place
        groups.setdefault(place.style if place is not None else town_style, []).append(name)
    return groups


def scenarios(args: argparse.Namespace) -> int:
    from towndrive.envs.scenarios import SCENARIOS, format_results, run_scenarios

    names = list(SCENARIOS) if args.scenario == "all" else [args.scenario]
    unknown = [n for n in names if n not in SCENARIOS]
    if unknown:
        raise ValueError(f"Unknown scenario {unknown[0]!r}; choose one of {', '.join(SCENARIOS)} or 'all'.")
    out = args.out or Path("out/scenarios")
    results = []
    for style, group in scenario_styles(names, args.town_style).items():
        # each scenario's agent gets the road priors of the town style it happens in (--road-priors style)
        spec = driver_spec(argparse.Namespace(**{**vars(args), "town_style": style}))
        results += run_scenarios(group, spec, make_config(args), out, video=not args.no_video,
                                 workers=min(args.workers, len(group)), ray=args.ray)
    results.sort(key=lambda r: names.index(r.name))
    print(format_results(args.driver, results))
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps([r.__dict__ for r in results], indent=2, default=str))
    print(f"Outputs in {out}/: results.json" + ("" if args.no_video else ", a video per scenario") + ".")
    return 0 if all(r.passed for r in results) else 1


def real_frames(args: argparse.Namespace) -> int:
    """The profile's agent on a real camera, a video file or a recorded episode, without the simulator."""
    from towndrive.agent.deploy.profiled_agent import run_profile

    out = args.out or Path("out/deploy_run")
    summary = run_profile(args.profile, args.camera, out, args.speed, args.show, args.alerts, args.serial)
    lat = summary["latency"]["total"]
    print(json.dumps({k: summary[k] for k in ("profile", "frames", "fps", "backends", "lane_frames", "warning_frames")}))
    print(f"total p50 {lat['p50_ms']:.1f} ms, p95 {lat['p95_ms']:.1f} ms (budget {lat['budget_ms']} ms); "
          f"overlay video and summary.json in {out}")
    return 0


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    args = parse_args(argv, prog)
    try:
        check_args(args)
        if args.camera and not args.profile:
            raise ValueError("--camera needs --profile (e.g. --profile cpu --camera drive.mp4).")
        if args.profile:
            from towndrive.agent.deploy.profiles import load_profile

            profile = load_profile(args.profile)
            if args.camera or profile.camera.source != "simulator":
                return real_frames(args)
            if profile.alerts.serial_port or profile.alerts.jsonl:
                raise ValueError(f"{profile.source_file}: the profile's alerts (serial_port, jsonl) are sent for real "
                                 "frames only; simulator runs write no alerts, so set them to null or add --camera.")
        if args.alerts or args.serial:
            raise ValueError("--alerts and --serial send the decisions of a real camera run (--profile NAME --camera "
                             "SOURCE); simulator runs write no alerts.")
        if args.record:
            return record(args)
        if args.evaluate:
            return evaluate(args)
        if args.scenario:
            return scenarios(args)
        return demo(args)
    except (ValueError, RuntimeError, FileNotFoundError, MissingExtra) as exc:
        print(f"{prog or 'drive.py'}: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
