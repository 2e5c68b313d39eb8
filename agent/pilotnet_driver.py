"""The ``pilotnet`` driver: PilotNet steers from the camera frame; a PID holds a constant target speed.

It sees only what a real car has: the camera frame, its own speed and the route command (the
conditional model picks its branch with it). Its steering changes at most as fast as the autopilot's
(``STEER_RATE_PER_S``), the rate the labels were recorded with; 0 turns the limit off. The speed is
the seed's assumption: constant, configurable, with an optional slow-down while the network asks for a
sharp turn. Inference runs through ONNX Runtime
(``backend="onnx"``, the default) or torch; both load the same shipped model.

A model file the user names is the only file opened: an ``.onnx`` runs on ONNX Runtime and carries what the
runtime needs besides the weights itself (the ``command`` input says the model is conditional; the crop is in
its ``pilotnet_meta`` metadata, or the default crop every ``train.py`` export has used), a ``.pt`` runs on torch.
Only the shipped default (``DEFAULT_MODEL``) stands for its pair, ``pilotnet.pt`` and ``pilotnet.onnx``.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from agent.autopilot import PID, STEER_RATE_PER_S
from agent.drivers import register
from agent.perception.pilotnet import Crop, preprocess, to_tensor
from agent.shipped import PILOTNET
from sim.ego import EgoVehicle

if TYPE_CHECKING:
    from envs.drive_env import DriveEnv

DEFAULT_MODEL = PILOTNET


class PilotNetModel:
    """A trained PilotNet behind one call, ``steer(rgb, command)``, on ONNX Runtime or torch."""

    def __init__(self, path: str | Path = DEFAULT_MODEL, backend: str | None = "onnx", threads: int = 1) -> None:
        path = Path(path)
        shipped = path.resolve() == DEFAULT_MODEL
        backend = backend or ("torch" if path.suffix == ".pt" and not shipped else "onnx")  # None: as the file says
        if backend not in ("onnx", "torch"):
            raise ValueError(f"Unknown PilotNet backend {backend!r}; use 'onnx' or 'torch'.")
        if shipped:  # the shipped pair, not a file the user named
            path = DEFAULT_MODEL.with_suffix(".onnx" if backend == "onnx" else ".pt")
        wanted = ".onnx" if backend == "onnx" else ".pt"
        if path.suffix != wanted:
            raise ValueError(f"{path}: the {backend} backend runs {wanted} files; give the model's {wanted} file or "
                             f"the {'torch' if backend == 'onnx' else 'onnx'} backend (--backend).")
        self.backend = backend
        if backend == "onnx":
            import json

            from agent.perception.onnx_runtime import onnx_session

            self.session = onnx_session(path, threads=threads, role="PilotNet")
            self.conditional = "command" in {i.name for i in self.session.get_inputs()}
            meta = self.session.get_modelmeta().custom_metadata_map.get("pilotnet_meta")
            try:
                self.crop = Crop(**json.loads(meta).get("crop", {})) if meta else Crop()
            except (ValueError, TypeError, AttributeError):
                raise ValueError(f"{path}: its pilotnet_meta metadata is not valid; re-export the model.") from None
        else:
            import torch

            from agent.training.pilotnet_training import load_model

            self.model, meta = load_model(path)
            self.conditional = bool(meta["conditional"])
            self.crop = Crop(**meta.get("crop", {}))
            torch.set_num_threads(threads)

    def steer(self, rgb: np.ndarray, command: int) -> float:
        x = to_tensor(preprocess(rgb, self.crop))
        cmd = np.array([int(command)], np.int64)
        if self.backend == "onnx":
            feeds = {"image": x.numpy()}
            if self.conditional:
                feeds["command"] = cmd
            return float(self.session.run(["steer"], feeds)[0][0, 0])
        import torch

        with torch.no_grad():
            y = self.model(x, torch.from_numpy(cmd)) if self.conditional else self.model(x)
        return float(y[0, 0])


@register("pilotnet")
class PilotNetDriver:
    """PilotNet steering plus a PID speed loop (see module docstring)."""

    name = "pilotnet"
    privileged = False

    def __init__(self, model: str | Path = DEFAULT_MODEL, backend: str = "onnx", target_speed_mps: float = 7.0,
                 turn_slowdown: float = 0.5, steer_rate_per_s: float = STEER_RATE_PER_S, threads: int = 1) -> None:
        self.net = PilotNetModel(model, backend, threads)
        self.target_speed = target_speed_mps
        self.turn_slowdown = turn_slowdown
        self.steer_rate = steer_rate_per_s
        self.speed_pid = PID(0.6, 0.1, 0.0)
        self.dt = 0.05
        self.last_steer = 0.0

    def reset(self, env: DriveEnv) -> None:
        self.dt = env.config.world.dt_s
        self.speed_pid.reset()
        self.last_steer = 0.0

    def target_speed_for(self, steer: float) -> float:
        """The cruise speed, lowered while the network steers hard (``turn_slowdown`` 0: always constant)."""
        return self.target_speed / (1.0 + self.turn_slowdown * 3.0 * abs(steer))

    def act(self, observation: dict[str, Any]) -> np.ndarray:
        steer = float(np.clip(self.net.steer(observation["image"], int(observation["command"])), -1.0, 1.0))
        if self.steer_rate > 0:  # the expert's gentle hands: frame-to-frame jitter of the network is not steering
            step = self.steer_rate * self.dt
            steer = min(self.last_steer + step, max(self.last_steer - step, steer))
        self.last_steer = steer
        speed = float(observation["speed"][0])
        accel = self.speed_pid(self.target_speed_for(steer) - speed, self.dt) * EgoVehicle.MAX_ACCEL_MPS2
        throttle = accel / EgoVehicle.MAX_ACCEL_MPS2 if accel >= 0 else accel / EgoVehicle.MAX_BRAKE_MPS2
        return np.array([steer, float(np.clip(throttle, -1.0, 1.0))], np.float32)
