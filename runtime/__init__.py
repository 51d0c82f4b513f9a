"""Torch-free GaussianTalker runtime: bundle -> onnxruntime graphs -> OpenGL splatting -> frames.

Everything an app needs is importable from here:

    from gaussiantalker.runtime import TalkingHead, HeadPose, GaussianTalkerError
"""

from gaussiantalker.sdk import __version__
from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.drive import FrameDrive, HeadPose
from gaussiantalker.sdk.errors import (
    AudioError,
    BundleError,
    CameraError,
    DriveError,
    GaussianTalkerError,
    RenderError,
    VideoError,
)
from gaussiantalker.sdk.video_formats import VideoPlan, plan_video

from .head import FrameOutput, HeadPoseSource, TalkingHead

__all__ = [
    "TalkingHead",
    "Camera",
    "HeadPose",
    "FrameDrive",
    "FrameOutput",
    "HeadPoseSource",
    "VideoPlan",
    "plan_video",
    "GaussianTalkerError",
    "AudioError",
    "BundleError",
    "CameraError",
    "DriveError",
    "RenderError",
    "VideoError",
    "__version__",
]
