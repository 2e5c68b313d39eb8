"""Where the shipped models live: one place for every driver, profile and tool that opens them.

Each shipped checkpoint's README (``data/models/README.md``) records the command and seed that made it.
"""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MODELS_DIR = ROOT / "data" / "models"
PILOTNET = MODELS_DIR / "pilotnet.pt"  # and pilotnet.onnx beside it
DETECTOR_ONNX = MODELS_DIR / "detector.onnx"
REFINER_ONNX = MODELS_DIR / "ped_refiner.onnx"
RL_POLICY = MODELS_DIR / "rl_ppo.zip"
