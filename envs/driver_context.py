"""What a driver is given at the start of an episode: the sensor rig and the time step, and the world only if it
is privileged.

Why: a camera-only driver must run the same on a recorded episode, a real camera and the simulator, so it is
handed only what a car knows of itself (its cameras, its time step, a way to ask for a mirror or corner frame), never the
environment. A privileged driver (the autopilot, the RL policy on ground-truth features) says so and gets the
world. ``DriverContext.of`` accepts an env made by ``gym.make`` (wrappers included), a ``DriveEnv`` or a context.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from towndrive.sim.spec import CAMERA, CameraConfig


@dataclass(frozen=True)
class DriverContext:
    camera: CameraConfig = CAMERA
    dt_s: float = 0.05
    stereo: bool = False  # the observation carries the stereo pair
    mirror_camera: CameraConfig | None = None  # the blind-spot cameras' model, where there are some
    mirror_frame: Callable[[str], np.ndarray] | None = None  # renders the "left" or "right" mirror camera now
    corner_camera: CameraConfig | None = None  # the cross-traffic cameras' model, where there are some
    corner_frame: Callable[[str], np.ndarray] | None = None  # renders the "left" or "right" corner camera now
    env: Any = None  # the unwrapped env: privileged drivers only
    world: Any = None  # its world (ground truth): privileged drivers only

    @classmethod
    def of(cls, source: Any, privileged: bool = False) -> DriverContext:
        """The context of ``source`` (a context, or an env with or without Gymnasium wrappers); the env and its
        world are included only for a ``privileged`` driver."""
        if isinstance(source, DriverContext):
            if privileged and source.world is None:
                raise ValueError("A privileged driver needs the world: give it the env, not a DriverContext.")
            return source
        env = getattr(source, "unwrapped", source)
        cfg = env.config
        look = getattr(env, "blind_spot_frame", None)
        corner = getattr(env, "corner_frame", None)
        renders = bool(getattr(cfg, "render_camera", False))
        return cls(camera=cfg.camera, dt_s=float(cfg.world.dt_s), stereo=bool(getattr(cfg, "observe_stereo", False)),
                   mirror_camera=getattr(cfg, "blind_spot_camera", None),
                   mirror_frame=look if renders and look is not None else None,
                   corner_camera=getattr(cfg, "corner_camera", None),
                   corner_frame=corner if renders and corner is not None else None,
                   env=env if privileged else None, world=getattr(env, "world", None) if privileged else None)
