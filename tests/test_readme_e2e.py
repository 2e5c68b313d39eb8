"""End to end: the README's main command (drive.py) writes a video, frames and a summary."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import imageio.v2 as imageio

ROOT = Path(__file__).resolve().parents[1]


def test_drive_py_writes_video_frames_and_summary(tmp_path):
    out = tmp_path / "drive"
    cmd = [sys.executable, "drive.py", "--seconds", "4", "--frames", "2", "--out", str(out), "--weather", "dusk"]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == 80 and summary["weather"] == "dusk"
    assert summary["driver"] == "agent"  # the main command runs the full agent on the shipped models
    assert len(summary["frames"]) == 2
    for name in summary["frames"]:
        frame = imageio.imread(out / name)
        assert frame.shape == (160, 320, 3) and frame.std() > 10
    reader = imageio.get_reader(out / "video.mp4")
    first = reader.get_data(0)
    assert first.shape[0] >= 160 + 320 and first.shape[1] >= 480  # the agent's overlay above camera and map
    assert sum(1 for _ in reader) >= 70
    reader.close()


def test_drive_py_rejects_unknown_weather_with_one_clear_line():
    done = subprocess.run([sys.executable, "drive.py", "--weather", "monsoon"], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 2
    assert "invalid choice: 'monsoon'" in done.stderr
