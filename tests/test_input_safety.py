"""Issue 26, one test per defect found by trying the project as a careful user and as an attacker: model files
that run code, a full disk and SIGTERM while recording, unchecked options, unchecked model files, unchecked
imported labels, and the smaller list (Gymnasium's contract, alerts, profiles, exports, summary, exit noise);
plus the renderer's memory per town. Each test fails on the code before the fix."""

from __future__ import annotations

import base64
import json
import os
import pickle
import shutil
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from towndrive.data.episodes import EpisodeWriter, list_episodes, next_episode_path, read_episode

ROOT = Path(__file__).resolve().parents[1]
MODELS = ROOT / "data" / "models"
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


class _Marker:
    """Unpickling this creates ``path``: the proof that a loader ran code from a file."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __reduce__(self):
        return (Path.touch, (self.path,))


def _frame(t: int, h: int = 32, w: int = 64) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w]
    return np.stack([(x * 4 + 7 * t) % 256, y * 8 % 256, np.full_like(x, 40 + t)], axis=-1).astype(np.uint8)


def _info(t: int) -> dict:
    return {"ego": {"x": 1.0 * t, "y": 2.0, "heading": 0.1}, "lane_offset_m": 0.05, "route": {"progress_m": 0.5 * t},
            "next_light": None, "time_s": 0.05 * t}


def _episode(path: Path, steps: int = 5, steer: float = 0.1) -> Path:
    writer = EpisodeWriter(path, {"seed": 0, "driver": "test", "dt_s": 0.05})
    for t in range(steps):
        writer.append({"image": _frame(t), "speed": np.array([3.0]), "command": 0}, np.array([steer, 0.2]), _info(t))
    return writer.close()


# ------------------------------------------------------------------------------------------ 1. model files
def test_1_a_crafted_checkpoint_runs_no_code(tmp_path: Path) -> None:
    import torch

    from towndrive.agent.perception.checkpoints import load_checkpoint
    from towndrive.agent.perception.detector import load_detector
    from towndrive.agent.perception.ped_refiner import load_refiner
    from towndrive.agent.perception.pilotnet import PilotNetModel, load_model
    from towndrive.agent.perception.sign_reader import load_sign_reader

    marker = tmp_path / "code_ran"
    evil = tmp_path / "x.pt"
    torch.save({"state_dict": {}, "conditional": True, "payload": _Marker(marker)}, evil)
    for load in (load_checkpoint, load_model, load_detector, load_refiner, load_sign_reader):
        with pytest.raises(ValueError, match=r"x\.pt is not a .*checkpoint"):
            load(evil)
    # --model x.onnx with a crafted x.pt beside it: only the file named is opened
    shutil.copy(MODELS / "pilotnet.onnx", tmp_path / "x.onnx")
    net = PilotNetModel(tmp_path / "x.onnx", backend="onnx")
    assert net.conditional and -1.5 < net.steer(np.zeros((160, 320, 3), np.uint8), 0) < 1.5
    assert not marker.exists()
    for name in ("pilotnet", "detector", "ped_refiner", "sign_reader"):  # the shipped checkpoints load safely
        assert "state_dict" in load_checkpoint(MODELS / f"{name}.pt", name)


def test_1_a_crafted_rl_zip_runs_no_code(tmp_path: Path) -> None:
    from towndrive.agent.rl_driver import load_policy

    marker = tmp_path / "code_ran"
    crafted = tmp_path / "rl_ppo.zip"
    with zipfile.ZipFile(MODELS / "rl_ppo.zip") as src, zipfile.ZipFile(crafted, "w") as dst:
        for item in src.infolist():
            payload = src.read(item.filename)
            if item.filename == "data":
                data = json.loads(payload)
                blob = base64.b64encode(pickle.dumps(_Marker(marker))).decode()
                for key in ("observation_space", "policy_class", "lr_schedule"):
                    data[key][":serialized:"] = blob  # what SB3's own load() would unpickle
                payload = json.dumps(data).encode()
            dst.writestr(item, payload)
    policy = load_policy(crafted)
    action, _ = policy.predict(np.zeros(24, np.float32), deterministic=True)
    assert action.shape == (2,) and not marker.exists()


# ------------------------------------------------------------------------------------------ 2. a full disk
_FULL_DISK = """
import errno, sys
import towndrive.data.episodes as E
budget = [int(sys.argv[1])]
class Disk:  # a disk with `budget` bytes free: writes beyond it fail as a full disk does
    def __init__(self, raw): self.raw = raw
    def __getattr__(self, name): return getattr(self.raw, name)
    def write(self, data):
        n = len(memoryview(data))
        if n > budget[0]:
            raise OSError(errno.ENOSPC, "No space left on device")
        budget[0] -= n
        return self.raw.write(data)
init = E._Sink.__init__
def patched(self, path):
    init(self, path)
    self._raw = Disk(self._raw)
E._Sink.__init__ = patched
import drive
sys.exit(drive.main(sys.argv[2:]))
"""


def test_2_a_full_disk_while_recording_keeps_finished_episodes_and_says_so(tmp_path: Path) -> None:
    out = tmp_path / "rec"
    args = ["--driver", "autopilot", "--record", str(out), "--episodes", "6", "--seconds", "1", "--width", "64",
            "--height", "32", "--traffic", "0"]
    run = subprocess.run([sys.executable, "-c", _FULL_DISK, "120000", *args], env=ENV, capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 1, run.stderr[-2000:]  # not 0, not 139 (the segfault)
    kept = list_episodes(out)
    assert 1 <= len(kept) < 6 and not list(out.glob("*.partial"))
    assert all(read_episode(p).steps > 0 for p in kept)
    last = run.stderr.strip().splitlines()[-1]
    assert f"the disk is full (no space left on device) writing {out}" in last and f"kept {len(kept)} finished" in last
    assert "Traceback" not in run.stderr


def test_2_a_full_disk_while_importing_removes_what_it_wrote(tmp_path: Path) -> None:
    import cv2

    src = tmp_path / "udacity"
    (src / "IMG").mkdir(parents=True)
    rows = []
    for t in range(30):
        name = f"center_2016_12_01_13_30_48_{100 + 50 * t:03d}.jpg"[:-4] + ".jpg"
        cv2.imwrite(str(src / "IMG" / name), _frame(t))
        rows.append(f"IMG/{name},,,0.1,0.5,0,10\n")
    (src / "driving_log.csv").write_text("".join(rows))
    code = _FULL_DISK.replace("import drive\nsys.exit(drive.main(sys.argv[2:]))",
                              "from data.__main__ import main\nsys.exit(main(sys.argv[2:]))")
    run = subprocess.run([sys.executable, "-c", code, "20000", "import-udacity", str(src), str(tmp_path / "dst")],
                         env=ENV, capture_output=True, text=True, timeout=120)
    assert run.returncode == 1 and "the disk is full" in run.stderr and "Traceback" not in run.stderr
    assert not any((tmp_path / "dst").glob("*"))


# ------------------------------------------------------------------------------------------ 3. SIGTERM, SIGHUP, SIGKILL
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_3_sigterm_and_sighup_while_recording_keep_finished_episodes(tmp_path: Path, sig: int) -> None:
    out = tmp_path / "rec"
    proc = subprocess.Popen([sys.executable, str(ROOT / "drive.py"), "--driver", "autopilot", "--record", str(out),
                             "--episodes", "200", "--seconds", "1", "--width", "64", "--height", "32", "--traffic", "0"],
                            env=ENV, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
    try:
        deadline = time.monotonic() + 120
        while not list(out.glob("episode_*.h5")) and time.monotonic() < deadline:
            time.sleep(0.2)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    kept = list_episodes(out)
    assert proc.returncode == 128 + sig and kept and not list(out.glob("*.partial"))
    assert f"Stopped by {signal.Signals(sig).name}: kept {len(kept)} finished episode(s)" in err
    assert all(read_episode(p).steps > 0 for p in kept)


def test_3_partial_leftovers_are_reported_and_never_overwritten(tmp_path: Path) -> None:
    from towndrive.data.__main__ import main
    from towndrive.data.summary import summarize

    folder = tmp_path / "ds"
    _episode(folder / "episode_00000.h5")
    leftover = folder / "episode_00001.h5.partial"  # a recording killed by SIGKILL left this
    leftover.write_bytes(b"half an episode")
    assert next_episode_path(folder).name == "episode_00002.h5"
    with pytest.raises(FileExistsError, match="left over"):
        EpisodeWriter(folder / "episode_00001.h5", {})
    assert leftover.read_bytes() == b"half an episode"
    assert summarize(folder)["partial"] == ["episode_00001.h5.partial"]
    assert main(["summary", str(folder), "--delete-partial"]) == 0 and not leftover.exists()


# ------------------------------------------------------------------------------------------ 4. options
@pytest.mark.parametrize(("options", "words"), [
    ({"traffic_density": 1e9}, "traffic_density must be a finite number from 0 to 5; got 1000000000.0"),
    ({"traffic_density": float("inf")}, "traffic_density must be"),
    ({"traffic_density": -1.0}, "traffic_density must be"),
    ({"traffic_density": float("nan")}, "traffic_density must be"),
    ({"town_seed": 1.5}, "town_seed must be an integer from 0 to 4294967295; got 1.5"),
    ({"town_seed": -1}, "town_seed must be an integer"),
    ({"start": ("nowhere", "else", 0)}, "start must be a lane index of town 0"),
    ({"start": 7}, "start must be a lane index"),
    ({"goal": ("a", "b")}, "goal must be an edge of town 0"),
])
def test_4_bad_reset_options_are_one_sentence(options: dict, words: str) -> None:
    from towndrive.envs.drive_env import DriveConfig, DriveEnv

    env = DriveEnv(DriveConfig(render_camera=False))
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match=words.replace("(", r"\(").replace(")", r"\)")):
        env.reset(seed=0, options=options)
    assert time.perf_counter() - t0 < 5.0  # 1e9 used to hang while memory grew past 4 GB
    env.close()


@pytest.mark.parametrize(("flags", "words"), [
    (["--width", "0"], "--width must be an integer from 8 to 4096; got 0."),
    (["--town-seed", "-1"], "--town-seed must be an integer from 0 to 4294967295; got -1."),
    (["--seconds", "-1"], "--seconds must be a finite number > 0; got -1.0."),
    (["--traffic", "inf"], "--traffic must be a finite number from 0 to 5; got inf."),
    (["--episodes", "0"], "--episodes must be an integer >= 1; got 0."),
])
def test_4_bad_flags_are_one_sentence_and_exit_2(flags: list[str], words: str, capsys: pytest.CaptureFixture) -> None:
    import drive

    assert drive.main([*flags, "--no-video"]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [f"drive.py: {words}"]


# ------------------------------------------------------------------------------------------ 5. ONNX files
def test_5_corrupt_or_mismatched_onnx_is_one_sentence_naming_the_file(tmp_path: Path) -> None:
    from towndrive.agent.perception.detector import OnnxDetector
    from towndrive.agent.perception.pilotnet import PilotNetModel

    broken = tmp_path / "broken.onnx"
    broken.write_bytes(b"\x08\x07garbage" * 10)
    with pytest.raises(ValueError, match=r"broken\.onnx is not a readable ONNX model"):
        PilotNetModel(broken)
    with pytest.raises(ValueError, match=r"detector\.onnx is not a PilotNet model \(it has inputs image"):
        PilotNetModel(MODELS / "detector.onnx")
    with pytest.raises(ValueError, match=r"pilotnet\.onnx is not a detector model"):
        OnnxDetector(MODELS / "pilotnet.onnx")
    shutil.copy(MODELS / "pilotnet.pt", tmp_path / "mine.pt")
    with pytest.raises(ValueError, match=r"mine\.pt: the onnx backend runs \.onnx files"):
        PilotNetModel(tmp_path / "mine.pt", backend="onnx")  # never opens a mine.onnx the user did not name
    assert PilotNetModel(tmp_path / "mine.pt", backend=None).backend == "torch"


# ------------------------------------------------------------------------------------------ 6. imported labels
@pytest.mark.parametrize(("steering", "words"), [("1e39", "steering must be a finite number from -1 to 1; got '1e39'"),
                                                 ("5", "steering must be a finite number from -1 to 1; got '5'")])
def test_6_import_udacity_refuses_labels_out_of_range(tmp_path: Path, steering: str, words: str) -> None:
    import cv2

    from towndrive.data.udacity import UdacityError, import_udacity

    src = tmp_path / "u"
    (src / "IMG").mkdir(parents=True)
    cv2.imwrite(str(src / "IMG" / "a.jpg"), _frame(0))
    (src / "driving_log.csv").write_text(f"IMG/a.jpg,,,0.1,0.5,0,10\nIMG/a.jpg,,,{steering},0.5,0,10\n")
    with pytest.raises(UdacityError, match=f"driving_log.csv line 2: {words}"):
        import_udacity(src, tmp_path / "dst")
    assert not (tmp_path / "dst").exists() or not any((tmp_path / "dst").iterdir())


def test_6_summary_reports_episodes_with_bad_labels(tmp_path: Path) -> None:
    from towndrive.data.summary import format_summary, summarize

    _episode(tmp_path / "ds" / "episode_00000.h5", steer=5.0)
    summary = summarize(tmp_path / "ds")
    assert summary["bad_labels"] == ["episode_00000.h5"] and "bad labels   ['episode_00000.h5']" in format_summary(summary)


# ------------------------------------------------------------------------------------------ 7. the smaller list
def test_7_gymnasium_contract_after_termination_and_close() -> None:
    import gymnasium as gym

    import towndrive.envs  # noqa: F401  (registers Drive-v0)

    env = gym.make("Drive-v0", render_camera=False, max_time_s=0.2, render_mode="rgb_array")
    env.reset(seed=0)
    done = False
    while not done:
        _, _, terminated, truncated, _ = env.step(np.zeros(2, np.float32))
        done = terminated or truncated
    with pytest.raises(RuntimeError, match="episode has ended"):
        env.step(np.zeros(2, np.float32))
    env.reset(seed=1)
    env.step(np.zeros(2, np.float32))  # a reset starts over
    env.close()
    with pytest.raises(RuntimeError, match="closed"):
        env.step(np.zeros(2, np.float32))
    with pytest.raises(RuntimeError, match="closed"):
        env.render()


def test_7_alerts_are_refused_in_simulator_runs(capsys: pytest.CaptureFixture) -> None:
    import drive

    assert drive.main(["--alerts", "-", "--no-video"]) == 2
    assert "--alerts and --serial send the decisions of a real camera run" in capsys.readouterr().err


@pytest.mark.parametrize("line", ["TDA,1,GG,-,0,0,0,-", "TDA,1,G,-,101,0,0,-", "TDA,1,G,-,0,500,0,-",
                                  "TDA,1,G,-,0,0,-5,-", "TDA,1,G,BF,0,0,5,-", "TDA,1,G,-,0,0,5,X"])
def test_7_alert_parser_refuses_out_of_spec_fields(line: str) -> None:
    from towndrive.agent.deploy.alerts import checksum, parse_line

    with pytest.raises(ValueError, match="must be"):
        parse_line(f"${line}*{checksum(line)}\r\n")
    with pytest.raises(ValueError, match="bytes or str, not NoneType"):
        parse_line(None)  # type: ignore[arg-type]


def test_7_export_udacity_leaves_no_orphan_images(tmp_path: Path) -> None:
    from towndrive.data.stopping import Stopped
    from towndrive.data.udacity import export_udacity

    _episode(tmp_path / "ds" / "episode_00000.h5", steps=8)
    calls = []

    def stop() -> None:
        calls.append(1)
        if len(calls) == 4:
            raise Stopped(signal.SIGTERM)

    with pytest.raises(Stopped):
        export_udacity(tmp_path / "ds", tmp_path / "out", stop=stop)
    assert not list((tmp_path / "out").rglob("*.jpg")) and not (tmp_path / "out" / "driving_log.csv").exists()


def test_7_non_utf8_profile_and_csv_name_the_file(tmp_path: Path) -> None:
    from towndrive.agent.deploy.profiles import ProfileError, load_profile, profile_from_dict
    from towndrive.data.udacity import UdacityError, read_log

    bad = tmp_path / "p.yaml"
    bad.write_bytes(b"name: x\ndescription: caf\xe9\n")
    with pytest.raises(ProfileError, match=r"p\.yaml: not UTF-8 text"):
        load_profile(bad)
    with pytest.raises(ProfileError, match="unknown key 'modles'; known keys here: name, description, export_dir, models"):
        profile_from_dict({"modles": {}})
    (tmp_path / "u").mkdir()
    (tmp_path / "u" / "driving_log.csv").write_bytes(b"a.jpg,,,0.1,0.5,0,10\n\xff\xfe,,,0,0,0,0\n")
    with pytest.raises(UdacityError, match=r"driving_log\.csv near line \d: not UTF-8"):
        read_log(tmp_path / "u")


def test_7_summary_decodes_frames_so_damaged_ones_are_caught(tmp_path: Path) -> None:
    import h5py

    from towndrive.data.summary import summarize

    path = _episode(tmp_path / "ds" / "episode_00000.h5", steps=6)
    with h5py.File(path, "r") as f:
        info = f["frames"].id.get_chunk_info(3)
    with open(path, "r+b") as f:  # the index still reads; one frame's compressed bytes do not
        f.seek(info.byte_offset + 4)
        f.write(b"\x00\xff" * 16)
    assert summarize(tmp_path / "ds", check_frames=False)["corrupt"] == []
    summary = summarize(tmp_path / "ds")
    assert summary["corrupt"] == ["episode_00000.h5"] and "cannot be decoded" in summary["problems"]["episode_00000.h5"]


def test_7_an_env_left_open_exits_quietly() -> None:
    code = ("from envs.drive_env import DriveEnv, DriveConfig\nfrom sim.render import CameraConfig\n"
            "env = DriveEnv(DriveConfig(camera=CameraConfig(width=64, height=32)))\nenv.reset(seed=0)\n"
            "import numpy as np\nenv.step(np.zeros(2))\nholder = [env]\nholder.append(holder)\n")
    run = subprocess.run([sys.executable, "-c", code], env=ENV, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and "Exception ignored" not in run.stderr and "Traceback" not in run.stderr


# ------------------------------------------------------------------------------------------ 8. memory per town
def test_8_renderers_of_new_towns_do_not_keep_memory() -> None:
    import ctypes
    import gc

    import towndrive.sim.render as render
    from towndrive.sim.world import WorldConfig, generate_town

    def rss_mb() -> float:
        with open("/proc/self/status") as f:
            return next(int(line.split()[1]) / 1024 for line in f if line.startswith("VmRSS:"))

    trim = ctypes.CDLL("libc.so.6").malloc_trim if sys.platform.startswith("linux") else (lambda _: 0)
    figures = []
    for k in range(9):
        town = generate_town(WorldConfig().town, 500 + k)
        renderer = render.SceneRenderer(town, seed=town.seed)
        renderer.close()
        del renderer, town
        gc.collect()
        trim(0)
        figures.append(rss_mb())
    assert not render._GROUND_MAPS  # nothing keeps a closed renderer's ground map
    # before: about 12 MB more per town (pybullet kept every static mesh) plus up to nine ground maps of 16 MB
    assert figures[-1] - figures[2] < 25.0, figures
