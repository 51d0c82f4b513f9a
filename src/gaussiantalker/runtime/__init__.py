"""Torch-free GaussianTalker runtime: a bundle's graphs on onnxruntime (or MNN), its Gaussians splatted with
OpenGL or the CPU tile splatter, frames out. `TalkingHead` is a front over the frame's stages (docs/embedding.md,
"Stages"): a Driver per rig (`FlameDriver`, `ArkitDriver`), a `FrameRenderer` with its splatter, a `Compositor`.

Everything an app needs is importable from here:

    from gaussiantalker.runtime import TalkingHead, HeadPose, GaussianTalkerError
    from gaussiantalker.runtime import BlendshapeDrive, load_motion, ARKIT_BLENDSHAPES   # ARKit speakers
    from gaussiantalker.runtime import FlameMotion, load_flame_motion   # FLAME motions (imported avatars)
    from gaussiantalker.runtime import RenderSettings, OutputSettings, BackendSettings   # grouped settings
    from gaussiantalker.runtime import LiveSession, LiveFrame, IdleMotion   # live sessions (TalkingHead.live)
    from gaussiantalker.runtime import FlameDriver, ArkitDriver, FrameRenderer, Compositor   # the stages
"""

from gaussiantalker.sdk import __version__
from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.drive import BlendshapeDrive, FrameDrive, HeadPose
from gaussiantalker.sdk.errors import (
    AudioError,
    BundleError,
    CameraError,
    DriveError,
    GaussianTalkerError,
    LiveError,
    RenderError,
    SettingsError,
    VideoError,
)
from gaussiantalker.sdk.flame_motion import FlameMotion, load_flame_motion
from gaussiantalker.sdk.motion import MotionTrack, load_motion
from gaussiantalker.sdk.render_settings import RenderSettings
from gaussiantalker.sdk.rig import ARKIT_BLENDSHAPES
from gaussiantalker.sdk.video_formats import VideoPlan, plan_video

from .compositor import Compositor
from .driver import ArkitDriver, FlameDriver
from .frame_renderer import FrameRenderer
from .head import FrameOutput, HeadPoseSource, TalkingHead
from .idle import IdleMotion
from .live import LiveFrame, LiveSession, LiveStats
from .motions import MotionSource
from .output import OutputView
from .settings import BackendSettings, OutputSettings
from .stages import open_driver

__all__ = [
    "TalkingHead",
    "FlameDriver",
    "ArkitDriver",
    "open_driver",
    "FrameRenderer",
    "Compositor",
    "Camera",
    "HeadPose",
    "FrameDrive",
    "BlendshapeDrive",
    "MotionTrack",
    "load_motion",
    "FlameMotion",
    "load_flame_motion",
    "ARKIT_BLENDSHAPES",
    "FrameOutput",
    "HeadPoseSource",
    "MotionSource",
    "RenderSettings",
    "OutputSettings",
    "BackendSettings",
    "OutputView",
    "VideoPlan",
    "plan_video",
    "GaussianTalkerError",
    "AudioError",
    "BundleError",
    "CameraError",
    "DriveError",
    "RenderError",
    "SettingsError",
    "VideoError",
    "LiveError",
    "LiveSession",
    "LiveFrame",
    "LiveStats",
    "IdleMotion",
    "__version__",
]
