"""The agent as a deployment profile runs it: in the simulator, or on real frames without the simulator.

``ProfiledAgent`` is the ``agent`` driver (``agent.agent_driver.AgentDriver``) built with what the profile says:
PilotNet and the detector on the profile's backends and precisions (``agent.deploy.backends``; the detector followed
by the shipped sign reader and pedestrian refiner, as in the simulator's agent), the detector every k frames (SORT
predicts in between), lanes and the stop line every k frames (the last result is reused in between), stereo every
m frames (box geometry gives the distances in between), and stereo matching timed apart from the rest of the
distance stage so that it can be held to its own budget.

``run_on_source`` drives it from a camera source (``agent.deploy.camera_sources``: a video file, a USB or CSI
camera, a recorded episode): each frame's decision goes to the alert outputs (``agent.deploy.alerts``: serial
line protocol, JSON lines), the overlay to a video (and a window with ``show``), and the per-stage
latencies, against the profile's budgets, to ``summary.json``. A real car has its speed from CAN or
odometry and its route command from navigation; a video file has neither, so they are given
(``speed_mps``, ``command``); recorded episodes carry both.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from towndrive.agent.agent_driver import AgentConfig, AgentDriver, Stages
from towndrive.agent.deploy.profiles import Profile, ProfileError
from towndrive.envs.driver_context import DriverContext


class EveryK:
    """A stage run on every k-th frame; in between, its last result is reused (lanes and stop line at a lower rate).
    Other attributes are the stage's own."""

    def __init__(self, stage: Any, every: int) -> None:
        self.stage, self.every, self.calls, self.last = stage, max(1, every), 0, None

    def detect(self, *args: Any, **kwargs: Any) -> Any:
        if self.calls % self.every == 0 or self.last is None:
            self.last = self.stage.detect(*args, **kwargs)
        self.calls += 1
        return self.last

    def __getattr__(self, name: str) -> Any:
        return getattr(self.stage, name)


class TimedStereo:
    """Stereo depth with its matching timed apart, so that the profile can hold it to its own budget."""

    def __init__(self, stereo: Any) -> None:
        self.stereo = stereo
        self.seconds = 0.0

    def disparity(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        t0 = time.perf_counter()
        out = self.stereo.disparity(left, right)
        self.seconds += time.perf_counter() - t0
        return out

    def __getattr__(self, name: str) -> Any:
        return getattr(self.stereo, name)


class ProfiledAgent:
    """The agent driver configured by a profile (see module docstring): an ``AgentDriver`` built from the
    profile's networks and module rates, by composition."""

    privileged = False

    def __init__(self, profile: Profile, **config_overrides: Any) -> None:
        from towndrive.agent.deploy.backends import open_detector, open_pilotnet

        if not profile.every("detector"):
            raise ProfileError(f"{profile.source_file}: the agent needs its detector; set modules.detector.enabled: true.")
        self.profile = profile
        config = AgentConfig(detect_every=profile.every("detector"),
                             distance="stereo" if profile.every("stereo") else "geometry", road=profile.road,
                             **config_overrides)
        self.agent = AgentDriver(config=config, net=open_pilotnet(profile),
                                 detect=open_detector(profile, config.score_threshold), stage_hook=self._rates)
        self.name = f"agent[{profile.name}]"

    def _rates(self, stages: Stages) -> Stages:
        """The profile's module rates and the stereo timer around the stages the agent built."""
        return replace(stages, lanes=EveryK(stages.lanes, self.profile.every("lanes") or 1),
                       stop=EveryK(stages.stop, self.profile.every("stop_line") or 1),
                       stereo=TimedStereo(stages.stereo) if stages.stereo is not None else None)

    def reset(self, context: Any) -> None:
        self.agent.reset(context)

    def act(self, observation: dict[str, Any]) -> np.ndarray:
        m = self.profile.every("stereo")
        if "stereo" in observation and (not m or self.agent._frame % m):
            observation = {k: v for k, v in observation.items() if k != "stereo"}  # geometry on this frame
        stereo = self.agent.stereo
        if stereo is not None:
            stereo.seconds = 0.0
        action = self.agent.act(observation)
        t = self.agent.timings[-1]
        t["stereo"] = (stereo.seconds if stereo is not None else 0.0) * 1000.0
        if "distance" in t:
            t["distance"] = max(0.0, t["distance"] - t["stereo"])
        return action

    def on_intervention(self) -> None:
        self.agent.on_intervention()

    def __getattr__(self, name: str) -> Any:  # timings, view, overlay, adas_summary, reason, ...
        return getattr(self.agent, name)


def frame_env(camera: Any, dt_s: float, stereo: bool) -> DriverContext:
    """What ``AgentDriver.reset`` takes (the sensor rig and time step), for frames from a real camera."""
    return DriverContext(camera=camera, dt_s=dt_s, stereo=stereo)


def budget_report(timings: list[dict[str, float]], budgets: dict[str, float]) -> dict[str, dict[str, float | None]]:
    """Per stage: p50, p95 (ms), the budget and the share of frames over it."""
    out: dict[str, dict[str, float | None]] = {}
    stages = sorted({k for t in timings for k in t}, key=lambda s: (s == "total", s))
    for stage in stages:
        ms = np.array([t.get(stage, 0.0) for t in timings])
        budget = budgets.get(stage)
        out[stage] = {"p50_ms": round(float(np.percentile(ms, 50)), 3), "p95_ms": round(float(np.percentile(ms, 95)), 3),
                      "budget_ms": budget, "over_budget": None if budget is None else round(float(np.mean(ms > budget)), 4)}
    return out


def run_on_source(profile: Profile, source: Any, out: Path | None = None, speed_mps: float = 8.0, command: int = 0,
                  max_frames: int | None = None, show: bool = False, alerts: Any = None,
                  agent: ProfiledAgent | None = None) -> dict[str, Any]:
    """Drive the profile's agent on a camera source (see module docstring); returns the summary."""
    from towndrive.agent.deploy.alerts import alert_from_view, open_alerts

    agent = agent or ProfiledAgent(profile)
    alerts = alerts or open_alerts(profile.alerts.serial_port, profile.alerts.baud, profile.alerts.jsonl)
    frames: Iterator[Any] = iter(source)
    t_read = time.perf_counter()
    first = next(frames, None)
    if first is None:
        raise ValueError("The camera source gave no frame.")
    dt = 1.0 / float(getattr(source, "fps", 20.0) or 20.0)
    agent.reset(frame_env(profile.camera_config(getattr(source, "eye_size", None)), dt, first.right is not None))
    writer = None
    if out is not None:
        from towndrive.envs.evaluation import video_writer

        out.mkdir(parents=True, exist_ok=True)
        writer = video_writer(out / "overlay.mp4", int(round(1.0 / dt)))
    timings: list[dict[str, float]] = []
    actions, warnings, lanes = [], {}, {"green": 0, "red": 0, "none": 0}
    t_start = time.perf_counter()
    frame = first
    try:
        while frame is not None:
            camera_ms = (time.perf_counter() - t_read) * 1000.0
            obs: dict[str, Any] = {"image": frame.image,
                                   "speed": np.array([frame.speed_mps if frame.speed_mps is not None else speed_mps], np.float32),
                                   "command": frame.command if frame.command is not None else command}
            if frame.right is not None:
                obs["stereo"] = (frame.image, frame.right)
            actions.append(agent.act(obs))
            t = dict(agent.timings[-1])
            t["camera"] = camera_ms  # the alert carries this frame's timings; its own sending time goes to the summary
            t0 = time.perf_counter()
            alert = alert_from_view(agent.view, frame.index, t)
            alerts.send(alert)
            t["alerts"] = (time.perf_counter() - t0) * 1000.0
            timings.append(t)
            lanes[alert.lane] += 1
            for w in alert.warnings:
                warnings[w] = warnings.get(w, 0) + 1
            if writer is not None or show:
                picture = agent.overlay()
                if writer is not None:
                    writer.append_data(picture)
                if show:
                    import cv2

                    try:
                        cv2.imshow(agent.name, cv2.cvtColor(picture, cv2.COLOR_RGB2BGR))
                    except cv2.error as exc:
                        raise RuntimeError("This OpenCV cannot open a window (opencv-python-headless, or no display); "
                                           "drop --show and watch the overlay video written to --out.") from exc
                    if cv2.waitKey(1) & 0xFF in (27, ord("q")):
                        break
            if max_frames is not None and len(timings) >= max_frames:
                break
            t_read = time.perf_counter()
            frame = next(frames, None)
    finally:
        if writer is not None:
            writer.close()
        alerts.close()
    wall = time.perf_counter() - t_start
    acts = np.array(actions)
    summary = {"profile": profile.name, "profile_file": profile.source_file, "frames": len(timings),
               "wall_s": round(wall, 2), "fps": round(len(timings) / wall, 1),
               "backends": {n: f"{m.backend} {m.precision}" for n, m in profile.models.items()},
               "detector_every": profile.every("detector"), "stereo_every": profile.every("stereo"),
               "lane_frames": lanes, "warning_frames": warnings,
               "mean_abs_steer": round(float(np.abs(acts[:, 0]).mean()), 4), "braking_frames": int((acts[:, 1] < 0).sum()),
               "latency": budget_report(timings, profile.budgets_ms),
               "video": str(out / "overlay.mp4") if out is not None else None}
    if out is not None:
        (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def camera_override(spec: str) -> dict[str, Any]:
    """``drive.py --camera``: ``usb:N``, ``csi:N``, an episode ``.h5`` or a video file, as profile camera fields."""
    kind, _, number = spec.partition(":")
    if kind in ("usb", "csi") and number.isdigit():
        return {"source": kind, ("device" if kind == "usb" else "sensor_id"): int(number)}
    path = Path(spec)
    if not path.is_file():
        raise FileNotFoundError(f"--camera {spec}: no such file; give a video file, an episode .h5, usb:N or csi:N.")
    return {"source": "episode" if path.suffix in (".h5", ".hdf5") else "video", "path": str(path.resolve())}


def run_profile(name: str, camera: str | None, out: Path, speed_mps: float = 8.0, show: bool = False,
                jsonl: str | None = None, serial_port: str | None = None, max_frames: int | None = None) -> dict[str, Any]:
    """``drive.py --profile NAME`` on real frames: the profile's camera (or ``camera``), alerts, overlay video."""
    from dataclasses import replace

    from towndrive.agent.deploy.alerts import open_alerts
    from towndrive.agent.deploy.camera_sources import open_source
    from towndrive.agent.deploy.profiles import load_profile

    profile = load_profile(name)
    if camera is not None:
        changes = camera_override(camera)
        if profile.camera.stereo == "simulator":
            changes["stereo"] = "none"
        profile = profile.with_camera(**changes)
    if jsonl is not None or serial_port is not None:
        profile = replace(profile, alerts=replace(profile.alerts, jsonl=jsonl or profile.alerts.jsonl,
                                                  serial_port=serial_port or profile.alerts.serial_port))
    agent = ProfiledAgent(profile)  # models first: a missing engine is reported before the camera opens
    source = open_source(profile)
    try:
        alerts = open_alerts(profile.alerts.serial_port, profile.alerts.baud, profile.alerts.jsonl)
        return run_on_source(profile, source, out, speed_mps, 0, max_frames, show, alerts, agent)  # closes alerts
    finally:
        source.close()
