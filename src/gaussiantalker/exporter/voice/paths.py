"""Where the committed voice models live (docs/voice.md): the files `gt-import` attaches by default."""

from __future__ import annotations

from pathlib import Path

MODELS = Path(__file__).resolve().parent / "models"
ARKIT_MODEL = MODELS / "arkit_voice.onnx"  # audio [1, S] -> blendshapes [1, T, 52]
FLAME_MODEL = MODELS / "flame_voice.onnx"  # audio [1, S] -> expression [1, T, 100], jaw_pose [1, T, 3]

__all__ = ["ARKIT_MODEL", "FLAME_MODEL", "MODELS"]
