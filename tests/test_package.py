"""The installable distribution: one importable name, package data inside, a console command, and an
environment that works without the optional parts (torch, ONNX, stable-baselines3)."""

from __future__ import annotations

import os
import subprocess
import sys
import sysconfig
import venv
import zipfile
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation", "-w", str(out),
                    str(ROOT)], check=True, cwd=out)
    return next(out.glob("towndrive-*.whl"))


def test_the_wheel_holds_one_package_with_its_models_and_profiles(wheel: Path) -> None:
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names}
    assert {t for t in tops if not t.endswith(".dist-info")} == {"towndrive"}, tops  # nothing generic at the top
    for shipped in ("pilotnet.pt", "pilotnet.onnx", "detector.onnx", "ped_refiner.onnx", "sign_reader.onnx", "rl_ppo.zip"):
        assert f"towndrive/data/models/{shipped}" in names
    assert "towndrive/agent/deploy/profiles/cpu.yaml" in names
    assert "towndrive/sim/spec.py" in names and "towndrive/agent/perception/detector.py" in names
    assert not any(n.startswith("towndrive/data/models/") and n.endswith(".jsonl") for n in names)  # no training logs
    entry = next(n for n in names if n.endswith("entry_points.txt"))
    assert "towndrive = towndrive.cli:run" in zipfile.ZipFile(wheel).read(entry).decode()


def test_the_installed_wheel_finds_its_models_and_profiles_outside_the_clone(wheel: Path, tmp_path: Path) -> None:
    """Installed (without dependencies, which this test's environment lends) in a fresh venv and run from an empty
    folder: the console command answers, profiles and shipped models are found in the package, and the env is made
    by its namespaced id."""
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=False).create(env_dir)
    python = env_dir / "bin" / "python"
    purelib = Path(subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                  check=True, capture_output=True, text=True).stdout.strip())
    # the dependencies come from this environment (its site-packages, not its editable install of the clone)
    (purelib / "lend.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--quiet", "--no-deps",
                    "--no-index", str(wheel)], check=True)
    work = tmp_path / "empty"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    script = (
        "import towndrive, gymnasium as gym\n"
        "from towndrive.agent.deploy.profiles import load_profile\n"
        "from towndrive.agent.shipped import PILOTNET\n"
        "assert '/work' not in towndrive.__file__ or 'venv' in towndrive.__file__, towndrive.__file__\n"
        "assert load_profile('cpu').name == 'cpu'\n"
        "assert PILOTNET.is_file() and 'site-packages' in str(PILOTNET), PILOTNET\n"
        "driver = towndrive.make_driver('agent')\n"
        "env = gym.make('towndrive/Drive-v0')\n"
        "print('ok', env.spec.id)\n")
    run = subprocess.run([str(python), "-c", script], cwd=work, env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "ok towndrive/Drive-v0" in run.stdout
    cli = subprocess.run([str(env_dir / "bin" / "towndrive"), "--help"], cwd=work, env=env, capture_output=True,
                         text=True, timeout=60)
    assert cli.returncode == 0 and "evaluate" in cli.stdout and "pybullet" not in cli.stdout + cli.stderr


BLOCK_OPTIONAL = ("import sys\n"
                  "for name in ('torch', 'onnxruntime', 'onnx', 'stable_baselines3', 'motmetrics', 'serial'):\n"
                  "    sys.modules[name] = None  # importing it now fails, as where it is not installed\n")


def test_the_environment_runs_without_the_optional_parts() -> None:
    """What ``pip install towndrive`` alone gives: the env, the autopilot and the evaluation, without torch."""
    script = BLOCK_OPTIONAL + (
        "import gymnasium as gym\n"
        "import towndrive\n"
        "env = gym.make('towndrive/Drive-v0')\n"
        "obs, info = env.reset(seed=0)\n"
        "metrics = towndrive.run_episode(env, towndrive.make_driver('autopilot'), seed=0, until_s=2.0)\n"
        "assert 0.0 <= metrics['driving_score'] <= 100.0\n"
        "print('ok')\n")
    run = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip().endswith("ok")


def test_an_optional_part_names_its_extra() -> None:
    """Asking for a driver that needs torch where it is not installed is one sentence naming the extra."""
    script = BLOCK_OPTIONAL + (
        "import towndrive\n"
        "try:\n"
        "    towndrive.make_driver('agent')\n"
        "except ImportError as exc:\n"
        "    print(exc)\n")
    run = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert "pip install 'towndrive[agent]'" in run.stdout, run.stdout + run.stderr


def test_gym_make_finds_the_env_by_module_prefix_from_an_empty_folder(tmp_path: Path) -> None:
    script = "import gymnasium as gym\nenv = gym.make('towndrive:towndrive/Drive-v0')\nprint(env.spec.max_episode_steps)\n"
    run = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert int(run.stdout.strip()) > 0


def test_gymnasium_image_wrappers_and_record_video_work_on_the_image_only_observation(tmp_path: Path) -> None:
    """``image_only=True``: a Box observation that Gymnasium's image wrappers and CnnPolicy take as it is."""
    import gymnasium as gym
    from gymnasium.wrappers import GrayscaleObservation, RecordVideo, ResizeObservation

    import towndrive  # noqa: F401
    from towndrive.envs import DriveConfig

    env = gym.make("towndrive/Drive-v0", config=DriveConfig(image_only=True), render_mode="rgb_array")
    assert isinstance(env.observation_space, gym.spaces.Box) and env.observation_space.shape == (160, 320, 3)
    env = RecordVideo(GrayscaleObservation(ResizeObservation(env, (84, 84))), str(tmp_path / "videos"), disable_logger=True)
    obs, info = env.reset(seed=0)
    assert obs.shape == (84, 84) and obs.dtype == np.uint8 and "speed_mps" in info["ego"]
    for _ in range(5):
        obs, *_ = env.step(np.array([0.0, 0.5], np.float32))
    env.close()
    assert list((tmp_path / "videos").glob("*.mp4")), "RecordVideo wrote no video"
