"""Torch-free GaussianTalker runtime: bundle -> onnxruntime graphs -> OpenGL splatting -> frames."""

from .head import TalkingHead

__all__ = ["TalkingHead"]
