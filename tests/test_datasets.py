"""Dataset tools: summary, Udacity export/import round trip, corrupt files and the ``python -m data`` CLI."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from towndrive.data.episodes import EpisodeError, EpisodeWriter, read_episode
from towndrive.data.summary import STEER_BINS, format_summary, summarize, write_histogram_png
from towndrive.data.udacity import MPH_TO_MPS, UdacityError, export_udacity, import_udacity

ROOT = Path(__file__).resolve().parents[1]
H, W = 66, 200


def _frame(t: int) -> np.ndarray:
    """A smooth synthetic image (JPEG-friendly) that changes from step to step."""
    y, x = np.mgrid[0:H, 0:W]
    img = np.stack([(x * 255 // (W - 1) + 7 * t) % 256, y * 255 // (H - 1), np.full_like(x, 40 + 10 * t)], axis=-1)
    return img.astype(np.uint8)


def _info(t: int) -> dict:
    return {"ego": {"x": 1.0 * t, "y": 2.0, "heading": 0.1}, "lane_offset_m": 0.05, "route": {"progress_m": 0.5 * t},
            "next_light": {"state": "red", "distance_m": 30.0} if t % 2 else None, "time_s": 0.05 * t}


# (driver, town_seed, weather, steps, command); steering/throttle_brake are chosen per step below
EPISODES = [("autopilot", 0, "clear", 6, 0), ("autopilot", 1, "rain", 4, 1), ("human", 0, "clear", 5, 2)]


def _write_dataset(folder: Path) -> list[np.ndarray]:
    actions = []
    for k, (driver, town, weather, steps, command) in enumerate(EPISODES):
        attrs = {"seed": k, "town_seed": town, "weather": weather, "driver": driver, "dt_s": 0.05,
                 "camera": {"width": W, "height": H}}
        writer = EpisodeWriter(folder / f"episode_{k:05d}.h5", attrs)
        acts = np.stack([np.linspace(-1.0, 1.0, steps), np.linspace(0.7, -0.3, steps)], axis=1).astype(np.float32)
        acts[0] = (0.1, 1 / 3)  # values without a short decimal form
        for t in range(steps):
            obs = {"image": _frame(t + 3 * k), "speed": np.array([5.0 + t]), "command": command}
            writer.append(obs, acts[t], _info(t))
        writer.close({"steps_done": steps})
        actions.append(acts)
    return actions


@pytest.fixture()
def dataset(tmp_path: Path) -> Path:
    folder = tmp_path / "ds"
    _write_dataset(folder)
    return folder


def test_summary_counts_and_png(tmp_path: Path) -> None:
    dataset = tmp_path / "ds"
    steer = np.concatenate([a[:, 0] for a in _write_dataset(dataset)]).astype(np.float64)
    s = summarize(dataset)
    assert s["episodes"] == 3 and s["frames"] == 15 and s["corrupt"] == []
    assert s["hours"] == pytest.approx(15 * 0.05 / 3600)
    assert s["drivers"] == {"autopilot": {"episodes": 2, "frames": 10}, "human": {"episodes": 1, "frames": 5}}
    assert s["towns"] == {"0": {"episodes": 2, "frames": 11}, "1": {"episodes": 1, "frames": 4}}
    assert s["weathers"]["clear"] == {"episodes": 2, "frames": 11}
    assert s["command_share"] == pytest.approx({"follow": 6 / 15, "left": 4 / 15, "right": 5 / 15})
    speeds = [5.0 + t for (_, _, _, n, _) in EPISODES for t in range(n)]
    assert s["mean_speed_mps"] == pytest.approx(np.mean(speeds))
    counts = s["steer_hist"]["counts"]
    assert len(counts) == STEER_BINS and sum(counts) == 15
    assert counts == np.histogram(steer, bins=STEER_BINS, range=(-1, 1))[0].tolist()
    assert counts[-1] == 3 and counts[10] == 1  # +1.0 counts in the last bin; 0.0 in the middle one
    text = format_summary(s)
    assert "frames       15" in text and "autopilot" in text and "corrupt      none" in text
    png = write_histogram_png(s, tmp_path / "out" / "hist.png")
    assert png.exists() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_udacity_round_trip(tmp_path: Path) -> None:
    src = tmp_path / "ds"
    actions = _write_dataset(src)
    udacity = tmp_path / "udacity"
    assert export_udacity(src, udacity) == 15
    lines = (udacity / "driving_log.csv").read_text().splitlines()
    assert len(lines) == 15 and not lines[0].startswith("center")
    first = lines[0].split(",")
    assert Path(first[0]).is_absolute() and first[0] == first[1] == first[2]
    assert first[3:5] == ["0.1", "0.33333334"] and first[5] == "0"

    back = tmp_path / "back"
    paths = import_udacity(udacity, back)
    assert [p.name for p in paths] == ["episode_00000.h5", "episode_00001.h5", "episode_00002.h5"]  # one per run
    for k, path in enumerate(paths):
        original, imported = read_episode(src / path.name), read_episode(path)
        np.testing.assert_array_equal(imported.actions[:, 0], actions[k][:, 0])
        np.testing.assert_allclose(imported.actions[:, 1], actions[k][:, 1], atol=1e-6, rtol=0)
        np.testing.assert_allclose(imported.speed, original.speed, atol=1e-3, rtol=0)
        assert imported.frames.shape == original.frames.shape
        mae = np.abs(imported.frames.astype(float) - original.frames.astype(float)).mean()
        assert mae < 3, f"{path.name}: JPEG error {mae:.2f} grey levels"
        assert (imported.command == 0).all()
        assert imported.attrs["driver"] == "udacity_import" and imported.attrs["seed"] == -1
        assert imported.attrs["camera"] == {"width": W, "height": H} and imported.attrs["weather"] == "unknown"
        assert not imported.attrs["side_cameras_available"]  # the export repeats the center path
        np.testing.assert_allclose(imported.truth["time_s"], np.arange(imported.steps) * 0.05, atol=1e-6)
        assert all(np.isnan(v).all() for name, v in imported.truth.items() if name != "time_s")


def _udacity_folder(folder: Path, rows: list[str], header: bool = False) -> Path:
    (folder / "IMG").mkdir(parents=True)
    names = set()
    for row in rows:
        names.update(_file_name(p) for p in row.split(",")[:3])
    for i, name in enumerate(sorted(names)):
        if name and "missing" not in name:
            cv2.imwrite(str(folder / "IMG" / name), np.full((160, 320, 3), 20 * i, np.uint8))
    text = ("center,left,right,steering,throttle,brake,speed\n" if header else "") + "\n".join(rows) + "\n"
    (folder / "driving_log.csv").write_text(text)
    return folder


def _file_name(text: str) -> str:
    """The file name of a Windows or POSIX path."""
    return text.strip().replace("\\", "/").rsplit("/", 1)[-1]


def test_import_original_layout_header_side_cameras_and_runs(tmp_path: Path) -> None:
    rows = [f"C:\\Users\\me\\IMG\\center_2016_12_01_13_30_48_{ms:03d}.jpg, /home/x/IMG/left_2016_12_01_13_30_48_{ms:03d}.jpg,"
            f" right_2016_12_01_13_30_48_{ms:03d}.jpg,0.25,0.5,0,20.5" for ms in (100, 200, 300)]
    rows.append("IMG/center_2016_12_01_13_40_00_000.jpg,IMG/left_2016_12_01_13_40_00_000.jpg,"
                "IMG/right_2016_12_01_13_40_00_000.jpg,-0.5,0,0.25,3")  # ten minutes later: a new run
    src = _udacity_folder(tmp_path / "u", rows, header=True)
    paths = import_udacity(src, tmp_path / "out")
    assert len(paths) == 2
    a, b = read_episode(paths[0]), read_episode(paths[1])
    assert a.steps == 3 and b.steps == 1 and a.frames.shape == (3, 160, 320, 3)
    np.testing.assert_allclose(a.actions[0], [0.25, 0.5])
    np.testing.assert_allclose(b.actions[0], [-0.5, -0.25])
    assert a.speed[0] == pytest.approx(20.5 * MPH_TO_MPS)
    assert a.attrs["side_cameras_available"]


def test_corrupt_episode_is_reported_by_name(dataset: Path) -> None:
    bad = dataset / "episode_00009.h5"
    bad.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    s = summarize(dataset)
    assert s["corrupt"] == ["episode_00009.h5"] and s["episodes"] == 3 and s["frames"] == 15
    assert "episode_00009.h5" in format_summary(s)
    with pytest.raises(EpisodeError, match="episode_00009.h5"):
        read_episode(bad)


def test_missing_image_and_bad_numbers_name_file_and_line(tmp_path: Path) -> None:
    ok = "center_a.jpg,left_a.jpg,right_a.jpg,0.1,0.2,0,10"
    src = _udacity_folder(tmp_path / "m", [ok, "center_missing.jpg,,,0.1,0.2,0,10"])
    with pytest.raises(UdacityError, match=r"driving_log.csv line 2: center image 'center_missing.jpg' not found"):
        import_udacity(src, tmp_path / "out")
    assert not (tmp_path / "out").exists() or not list((tmp_path / "out").iterdir())  # nothing half-written
    src = _udacity_folder(tmp_path / "n", [ok, "center_a.jpg,left_a.jpg,right_a.jpg,0.1,fast,0,10"])
    with pytest.raises(UdacityError, match=r"driving_log.csv line 2: throttle is 'fast', not a number"):
        import_udacity(src, tmp_path / "out")
    with pytest.raises(UdacityError, match="driving_log.csv: no such file"):
        import_udacity(tmp_path, tmp_path / "out")


def _cli(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", "towndrive.data", *args], capture_output=True, text=True, cwd=ROOT, env=env,
                          timeout=60)


def test_cli_summary_and_errors(dataset: Path, tmp_path: Path) -> None:
    png = tmp_path / "hist.png"
    done = _cli("summary", str(dataset), "--png", str(png))
    assert done.returncode == 0, done.stderr
    assert "frames       15" in done.stdout and png.exists()
    done = _cli("import-udacity", str(tmp_path / "nowhere"), str(tmp_path / "out"))
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert "driving_log.csv: no such file" in done.stderr and len(done.stderr.strip().splitlines()) == 1
