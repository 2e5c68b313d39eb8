"""The driver interface and the registry that finds drivers by name.

A driver is started once per episode (``reset(context)``) and then asked for an action for each observation
(``act(observation)``). The context (``envs.driver_context.DriverContext``) carries the sensor rig and time step;
a driver that reads ground truth is *privileged*, says so with ``privileged = True`` and finds the world in the
context. The others use only the observation (camera frames, speed, route command), as a real car would. Every
built-in driver also accepts the env itself (with or without Gymnasium wrappers) in place of the context.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:
    from towndrive.envs.driver_context import DriverContext


@runtime_checkable
class Driver(Protocol):
    """What drive.py and the evaluation need from a driver."""

    name: str
    privileged: bool

    def reset(self, context: DriverContext) -> None:
        """Start an episode (the env is already reset)."""

    def act(self, observation: dict[str, Any]) -> np.ndarray:
        """``[steer, throttle_brake]`` in [-1, 1] for this observation."""

    # Optional: ``on_intervention()``, called by the evaluation after the safety driver has put the car back
    # on its lane (a driver that tracks or dead-reckons state starts it afresh there).
    # Optional: ``set_episode_index(k)``, called before ``reset`` with the episode's place in its run, so a driver
    # with per-episode randomness draws it from the index, not from how many episodes this instance has seen
    # (an episode then gives the same result on any worker process, envs.parallel).


_REGISTRY: dict[str, Callable[..., Driver]] = {}


def register(name: str) -> Callable[[Callable[..., Driver]], Callable[..., Driver]]:
    """Class decorator: make a driver constructible by name."""

    def wrap(factory: Callable[..., Driver]) -> Callable[..., Driver]:
        _REGISTRY[name] = factory
        return factory

    return wrap


def make_driver(name: str, **kwargs: Any) -> Driver:
    """Build a registered driver; an unknown name is one clear error listing the known ones."""
    _load_builtin()
    if name not in _REGISTRY:
        raise ValueError(f"Unknown driver {name!r}; choose one of {', '.join(sorted(_REGISTRY))}.")
    return _REGISTRY[name](**kwargs)


# The built-in drivers, by the module and class that make them: imported only when asked for (pygame, torch and
# stable-baselines3 load only for the drivers that need them), and without the drivers importing this registry.
BUILTIN = {
    "agent": "towndrive.agent.agent_driver:AgentDriver",
    "autopilot": "towndrive.agent.autopilot:Autopilot",
    "gamepad": "towndrive.agent.human:GamepadDriver",
    "keyboard": "towndrive.agent.human:KeyboardDriver",
    "pilotnet": "towndrive.agent.pilotnet_driver:PilotNetDriver",
    "rl": "towndrive.agent.rl_driver:RLDriver",
}


def _load_builtin() -> None:
    """Put the built-in drivers' factories into the registry (each imported on first use)."""
    for name, target in BUILTIN.items():
        if name not in _REGISTRY:
            _REGISTRY[name] = _lazy(target)


def _lazy(target: str) -> Callable[..., Driver]:
    def make(**kwargs: Any) -> Driver:
        from towndrive.extras import import_for

        module, _, cls = target.partition(":")
        return getattr(import_for(module, f"The {cls} driver"), cls)(**kwargs)

    return make
