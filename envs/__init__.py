"""Gymnasium environments over the simulator. Importing this package registers ``Drive-v0``."""

from gymnasium.envs.registration import register, registry

from envs.drive_env import DriveConfig, DriveEnv

__all__ = ["DriveConfig", "DriveEnv"]

if "Drive-v0" not in registry:
    register(id="Drive-v0", entry_point="envs.drive_env:DriveEnv")
