"""Where the shipped models live: one place for every driver, profile and tool that opens them.

Each shipped checkpoint's README (``data/models/README.md``) records the command and seed that made it.
"""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MODELS_DIR = ROOT / "data" / "models"
PILOTNET = MODELS_DIR / "pilotnet.pt"  # and pilotnet.onnx beside it
DETECTOR_ONNX = MODELS_DIR / "detector.onnx"  # cars, trucks, pedestrians, lights (six classes; `--no-signs`)
DETECTOR_SIGNS_ONNX = MODELS_DIR / "detector_signs.onnx"  # the default: the six and the four road-sign classes
REFINER_ONNX = MODELS_DIR / "ped_refiner.onnx"
SIGN_READER_ONNX = MODELS_DIR / "sign_reader.onnx"  # reads which road sign a detector sign box holds
RL_POLICY = MODELS_DIR / "rl_ppo.zip"
