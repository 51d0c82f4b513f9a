"""What a TalkingHead's frames will be, decided from the bundle's manifest and OutputSettings alone (nothing decoded,
no graph loaded): the camera they are seen through, whether they are composited into the reference clip, and the
checked video plan for them. An app (samples/play.py) can so refuse a bad output before loading the speaker.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

from gaussiantalker.sdk.bundle import Bundle
from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.errors import BundleError, CameraError, RenderError, VideoError
from gaussiantalker.sdk.reference_clip import ClipLayout, ReferenceClipError
from gaussiantalker.sdk.video_formats import VideoPlan, plan_video

from .settings import OutputSettings

COMPOSITE_ALPHA_MESSAGE = ("a composited frame is opaque (the reference clip fills it); alpha=True needs the bare "
                           "head: TalkingHead(..., composite=False)")


@dataclass(frozen=True, eq=False)
class OutputView:
    """The camera a head's frames are drawn with (at the output size) and whether they are composited."""

    camera: Camera
    composite: bool

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of every frame."""
        return self.camera.width, self.camera.height

    def plan_video(self, path: str | os.PathLike, *, alpha: bool = False, codec: str | None = None,
                   crf: int | None = None, preset: str | None = None, container: str | None = None) -> VideoPlan:
        """The checked plan for a video of these frames (`sdk.video_formats.plan_video`, VideoError if it cannot
        work; RenderError for alpha on composited frames, which are opaque)."""
        if self.composite and alpha:
            raise RenderError(COMPOSITE_ALPHA_MESSAGE)
        return plan_video(path, self.size, alpha=alpha, codec=codec, crf=crf, preset=preset, container=container)

    def video_plan(self, path: str | os.PathLike | VideoPlan, *, alpha: bool | None, **options) -> VideoPlan:
        """`path` planned for these frames (`plan_video`), or a given VideoPlan checked against them (VideoError if
        it is for another size, or options are given beside it; RenderError for alpha on composited frames)."""
        if not isinstance(path, VideoPlan):
            return self.plan_video(path, alpha=bool(alpha), **options)
        given = [f"{name}={value!r}" for name, value in options.items() if value is not None]
        if given:
            raise VideoError(f"a VideoPlan already sets the output; give it or {', '.join(given)}, not both")
        if alpha is not None and bool(alpha) != path.alpha:
            raise VideoError(f"alpha={alpha!r} but the VideoPlan has alpha={path.alpha}; give it once")
        if self.composite and path.alpha:
            raise RenderError(COMPOSITE_ALPHA_MESSAGE)
        if tuple(path.size) != self.size:
            raise VideoError(f"the VideoPlan is for {path.size[0]}x{path.size[1]} frames but this head renders "
                             f"{self.size[0]}x{self.size[1]} (plan it with head.plan_video)")
        return path


def output_view(bundle: Bundle, output: OutputSettings) -> OutputView:
    """The frames a head with `output` makes from `bundle`: composited (at the reference clip's camera, resized to
    `output.resolution`) when the bundle has a clip and `output.composite` is not False, else the bare head at
    `output.camera` or the bundle's camera, resized to `output.resolution`."""
    has_clip = "reference" in bundle.manifest
    composite = has_clip if output.composite is None else output.composite
    if composite:
        if not has_clip:
            raise RenderError(f"{bundle.path}: composite=True needs a bundle with a reference clip (export a "
                              "speaker that carries one, docs/compositing.md)")
        if output.camera is not None:
            raise RenderError("a composited frame is seen through the reference clip's camera; pass "
                              "composite=False to render the bare head with your own camera")
        try:
            camera = ClipLayout.from_dict(bundle.manifest["reference"]).camera
        except ReferenceClipError as exc:
            raise BundleError(f"{bundle.path}: manifest 'reference' is invalid: {exc}") from None
        # As ReferenceClip.camera: the clip's own camera unless the output size differs.
        if output.resolution is not None and output.resolution != (camera.width, camera.height):
            camera = camera.resized(*output.resolution)
        return OutputView(camera, True)
    camera = output.camera
    if camera is None:
        try:
            camera = Camera.from_dict(bundle.manifest["camera"])
        except (CameraError, KeyError, TypeError) as exc:
            raise BundleError(f"{bundle.path}: manifest 'camera' section is invalid: {exc}") from None
    if output.resolution is not None:
        camera = camera.resized(*output.resolution)
    return OutputView(camera, False)


__all__ = ["OutputView", "output_view"]
