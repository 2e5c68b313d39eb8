"""Gymnasium environments over the simulator: ``towndrive/Drive-v0`` (registered by ``import towndrive``).

``DriveConfig`` and ``DriveEnv`` are imported on first use, so that light modules of this package (the metrics,
the evaluation rules' flags) load without the simulator.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import towndrive  # noqa: F401  (registers towndrive/Drive-v0 and Drive-v0)

if TYPE_CHECKING:
    from towndrive.envs.drive_env import DriveConfig, DriveEnv

__all__ = ["DriveConfig", "DriveEnv"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from towndrive.envs import drive_env

        return getattr(drive_env, name)
    raise AttributeError(f"module 'towndrive.envs' has no attribute {name!r}")
