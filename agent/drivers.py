"""The driver interface and the registry that finds drivers by name.

A driver is handed the environment once per episode (``reset(env)``) and then asked for an action
for each observation (``act(observation)``). A driver that reads ground truth (``env.world``) is
*privileged* and says so with ``privileged = True``; the others use only the observation (camera
frames, speed, route command), as a real car would.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:
    from envs.drive_env import DriveEnv


@runtime_checkable
class Driver(Protocol):
    """What drive.py and the evaluation need from a driver."""

    name: str
    privileged: bool

    def reset(self, env: DriveEnv) -> None:
        """Start an episode in ``env`` (already reset)."""

    def act(self, observation: dict[str, Any]) -> np.ndarray:
        """``[steer, throttle_brake]`` in [-1, 1] for this observation."""

    # Optional: ``on_intervention()``, called by the evaluation after the safety driver has put the car back
    # on its lane (a driver that tracks or dead-reckons state starts it afresh there).


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


def _load_builtin() -> None:
    """Import the modules whose drivers register themselves (lazily: pygame loads only when asked for)."""
    import agent.agent_driver  # noqa: F401
    import agent.autopilot  # noqa: F401
    import agent.human  # noqa: F401
    import agent.pilotnet_driver  # noqa: F401
    import agent.rl_driver  # noqa: F401
