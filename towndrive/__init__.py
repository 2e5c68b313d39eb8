"""towndrive: a town driving simulator (pybullet, CPU) with a Gymnasium environment and a self-driving agent stack.

The installed package holds four parts, each a subpackage: ``towndrive.sim`` (towns, world, renderer),
``towndrive.envs`` (the Gymnasium env, evaluation), ``towndrive.agent`` (drivers, perception, decision, training,
deployment) and ``towndrive.data`` (recorded episodes). The small public API is here::

    import gymnasium as gym
    from towndrive import make_driver, run_episode

    env = gym.make("towndrive/Drive-v0")
    metrics = run_episode(env, make_driver("agent"), seed=0)  # a dict; no files written

Importing ``towndrive`` registers ``towndrive/Drive-v0`` (Gymnasium 1.x has no plugin entry points, so
``gym.make("towndrive:towndrive/Drive-v0")`` imports it for you). Nothing heavy is imported until it is used.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

# In a clone the parts are the repository's top-level folders (sim/, envs/, agent/, data/); the wheel puts them
# inside this package. Either way they are found as towndrive.sim, towndrive.envs, ...
_ROOT = Path(__file__).resolve().parent.parent
if not (Path(__file__).resolve().parent / "sim").is_dir() and (_ROOT / "sim" / "spec.py").is_file():
    __path__.append(str(_ROOT))  # type: ignore[name-defined]  # noqa: F821

__version__ = "0.2.0"
ENV_ID = "towndrive/Drive-v0"

if TYPE_CHECKING:
    from towndrive.agent.drivers import Driver


def _register() -> None:
    from gymnasium.envs.registration import register, registry

    from towndrive.sim.spec import EPISODE_S, STEP_S

    for env_id in (ENV_ID, "Drive-v0"):  # Drive-v0: the id of earlier releases
        if env_id not in registry:  # max_episode_steps: the default config's time limit (the env also truncates)
            register(id=env_id, entry_point="towndrive.envs.drive_env:DriveEnv",
                     max_episode_steps=round(EPISODE_S / STEP_S))


_register()


def make_driver(name: str, **kwargs: Any) -> Driver:
    """A driver by name (``agent``, ``autopilot``, ``pilotnet``, ``rl``, ``keyboard``, ``gamepad``)."""
    from towndrive.agent.drivers import make_driver as make

    return make(name, **kwargs)


def run_episode(env: Any, driver: Any, seed: int = 0, options: dict[str, Any] | None = None,
                until_s: float | None = None) -> dict[str, Any]:
    """Drive one evaluation episode of ``env`` (made by ``gym.make`` or ``DriveEnv``) with ``driver`` and return
    its metrics (driving score, route completion, infractions, ...) as a dict; nothing is written to disk. A safety
    driver takes over when the car leaves its lane or collides, as in every towndrive evaluation."""
    from towndrive.envs.evaluation import run_episode as run
    from towndrive.envs.metrics import episode_metrics

    return episode_metrics(run(env.unwrapped, driver, seed, options=options, until_s=until_s))


__all__ = ["ENV_ID", "make_driver", "run_episode", "__version__"]
