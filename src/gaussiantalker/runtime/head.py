"""The embedding API: load a bundle, turn audio, a motion or explicit parameters into frames, write a video.

    head = TalkingHead("speaker.gtb", resolution=(512, 512))
    for frame in head.frames("speech.wav"):      # uint8 [H, W, 3], one per video frame, streamed
        ...
    head.write_video("talk.mp4", "speech.wav")   # audio muxed in

`TalkingHead` is a front over the frame's stages (docs/embedding.md, "Stages"): `head.driver` (audio or a motion ->
drives), `head.frame_renderer` (drives -> Gaussians -> pixels) and `head.compositor` (into the reference clip; None
for the bare head), built from the bundle by runtime/stages.py. Settings come in groups (runtime/settings.py):

    head = TalkingHead("speaker.gtb", output_settings=OutputSettings(resolution=(512, 512)),
                       render_settings=RenderSettings(render_scale=0.5), backend_settings=BackendSettings("mnn"))
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from contextlib import closing
from pathlib import Path
from typing import Literal

import numpy as np

from gaussiantalker.sdk.bundle import Bundle
from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.errors import RenderError
from gaussiantalker.sdk.render_settings import RenderSettings
from gaussiantalker.sdk.rig import ARKIT_RIG, FLAME_RIG, check_drive_rig
from gaussiantalker.sdk.video import VideoWriter
from gaussiantalker.sdk.video_formats import VideoPlan

from .compositor import check_composited_output
from .driver import AudioSource, Drive, HeadPoseSource
from .frame_loops import bare_frames, composited_frames, write_frames
from .motions import MotionSource
from .output import OutputView, output_view
from .playback import playback, video_frames
from .renamed import renamed_attribute, settings_groups
from .settings import BackendSettings, OutputSettings, merged_backend, merged_output
from .stages import build_stages, render_settings_by_splatter
from .translate import SILENCE_GATE_DBFS

# What a frame is returned as: "uint8" [H, W, 3] (the composited frame when compositing), "float" float32 [H, W, 3]
# (C + T * background, unclamped), "rgba" uint8 [H, W, 4] straight colour and coverage 1 - T (for overlays and videos
# with alpha), "rgba_float" float32 [H, W, 4] premultiplied (C, 1 - T) as splatted, or (render only) "semantic"
# uint8 [H, W, 3]: each Gaussian in its region's colour over black (`head.frame_renderer.regions`).
FrameOutput = Literal["uint8", "float", "rgba", "rgba_float", "semantic"]


class TalkingHead:
    """A loaded bundle as its stages (driver, frame renderer, compositor): audio, a motion or parameters in, frames
    out."""

    def __init__(self, bundle: str | os.PathLike | Bundle, *, render_settings: RenderSettings | None = None,
                 output_settings: OutputSettings | None = None, backend_settings: BackendSettings | None = None,
                 backend: str | None = None, resolution: tuple[int, int] | None = None, camera: Camera | None = None,
                 background=None, composite: bool | None = None, threads: int | None = None,
                 shader_target: str | None = None, renderer: str | None = None, render_scale: float | None = None,
                 render_target: str | None = None, sort_interval: int | None = None, sort_key_bits: int | None = None,
                 alpha_min: float | None = None, max_draw_pixels: int | None = None, pipeline: bool | None = None,
                 gl_context=None, silence_gate_dbfs: float | None = SILENCE_GATE_DBFS,
                 render: RenderSettings | None = None, output: OutputSettings | None = None,
                 transmittance_min: float | None = None) -> None:
        """Three settings groups, each None for the bundle's defaults (docs/embedding.md): `render_settings`
        (render scale, framebuffer precision, sort interval and key bits, graph threads, the CPU splatter's alpha
        cut and transmittance stop, a cap on drawn pixels; docs/precision.md),
        `output_settings` (resolution, camera, background, composite: compositing defaults to whether the bundle has
        a reference clip, docs/compositing.md) and `backend_settings` (graph backend name, threads, shader_target,
        renderer "gl" | "cpu" | "auto", pipeline). `backend` names the graph backend ("onnxruntime" or "mnn").

        Every other keyword but `gl_context` (a moderngl context to draw in; None: a headless one of its own) and
        `silence_gate_dbfs` (audio windows quieter than this RMS fade to the neutral face; None: off) is a shortcut
        for one group field; one given both ways with two values is a SettingsError naming both. `render=` and
        `output=` are the old names of the first two groups."""
        self.bundle = bundle if isinstance(bundle, Bundle) else Bundle(bundle)
        render_settings, output_settings, backend = settings_groups(render, output, backend, render_settings,
                                                                    output_settings, backend_settings)
        self.output_settings = merged_output(output_settings, resolution=resolution, camera=camera,
                                             background=background, composite=composite)
        merged = merged_backend(backend, threads=threads, shader_target=shader_target, renderer=renderer,
                                pipeline=pipeline)
        label = "backend.threads" if isinstance(backend, BackendSettings) and threads is None else "threads"
        by_splatter = render_settings_by_splatter(self.bundle, render_settings, merged.threads, label,
                                                  render_scale=render_scale, render_target=render_target,
                                                  sort_interval=sort_interval, sort_key_bits=sort_key_bits,
                                                  alpha_min=alpha_min, max_draw_pixels=max_draw_pixels,
                                                  transmittance_min=transmittance_min)
        stages = build_stages(self.bundle, by_splatter, self.output_settings, merged, gl_context=gl_context,
                              silence_gate_dbfs=silence_gate_dbfs)
        self.render_settings, self.backend_settings = stages.render, stages.backend
        self.driver, self.frame_renderer, self.compositor = stages.driver, stages.frame_renderer, stages.compositor
        self.renderer, self.reference, self.timings = stages.renderer, stages.reference, stages.timings

    def __getattr__(self, name: str):
        if name.startswith("__"):
            raise AttributeError(name)
        return renamed_attribute(self, name)  # the names before the stages, warned once (runtime/renamed.py)

    @property
    def camera(self) -> Camera:
        """The camera every frame is seen through (the reference clip's when compositing); assign one any time."""
        return self.frame_renderer.camera

    @camera.setter
    def camera(self, camera: Camera) -> None:
        self.frame_renderer.camera = camera

    @property
    def fps(self) -> int:
        """Video frames per second of this speaker."""
        return self.driver.fps

    @property
    def sample_rate(self) -> int:
        """Audio sample rate (Hz) this speaker's audio is resampled to."""
        return self.driver.sample_rate

    @property
    def frame_size(self) -> tuple[int, int]:
        """(width, height) of this head's frames."""
        return self.camera.width, self.camera.height

    @classmethod
    def output_view(cls, bundle: str | os.PathLike | Bundle, output_settings: OutputSettings | None = None, *,
                    resolution: tuple[int, int] | None = None, camera: Camera | None = None, background=None,
                    composite: bool | None = None) -> OutputView:
        """The camera and compositing a head with these output settings would have, from the manifest alone:
        `.size`, `.composite`, `.plan_video(...)` check an output before the speaker is loaded."""
        bundle = bundle if isinstance(bundle, Bundle) else Bundle(bundle)
        return output_view(bundle, merged_output(output_settings, resolution=resolution, camera=camera,
                                                 background=background, composite=composite))

    def plan_video(self, path: str | os.PathLike, *, alpha: bool = False, codec: str | None = None,
                   crf: int | None = None, preset: str | None = None, container: str | None = None) -> VideoPlan:
        """The checked plan for writing this head's frames to `path` (`write_video` takes it); VideoError if it
        cannot work (docs/video.md), RenderError for alpha on composited frames."""
        return OutputView(self.camera, self.compositor is not None).plan_video(
            path, alpha=alpha, codec=codec, crf=crf, preset=preset, container=container)

    def drives(self, audio: AudioSource | None = None, sample_rate: int | None = None,
               head_pose: HeadPoseSource = None, *, motion: MotionSource = None) -> Iterator[Drive]:
        """One drive per frame: of an audio clip (through the translator), else of `motion` (a motion file, track or
        table; None: the bundle's own motion; see `head.driver.motion`)."""
        if audio is None:
            yield from self.driver.motion_drives(motion, head_pose)
        else:
            yield from self.driver.drives(audio, sample_rate, head_pose)

    def frames(self, audio: AudioSource | None = None, sample_rate: int | None = None,
               head_pose: HeadPoseSource = None, output: FrameOutput = "uint8", *,
               motion: MotionSource = None) -> Iterator[np.ndarray]:
        """Frames of an audio clip at the speaker's fps (or, without audio, of `motion` as in `drives`), yielded
        one at a time and pipelined (runtime/frame_loops.py). Composited heads composite each audio frame into the
        reference clip's picture at its index; a motion plays on the bare head."""
        pipelined = self.backend_settings.pipeline is not False
        if audio is None or self.compositor is None:
            yield from bare_frames(self.frame_renderer, self.drives(audio, sample_rate, head_pose, motion=motion),
                                   output, pipelined)
            return
        check_composited_output(self.compositor, output)
        if head_pose is not None:
            raise RenderError("a composited head follows the reference clip's pose track (any other pose "
                              "would misalign it with the clip); pass composite=False to set head_pose")
        yield from composited_frames(self.frame_renderer, self.compositor, self.drives(audio, sample_rate), pipelined)

    def render(self, drive: Drive, output: FrameOutput = "uint8", reference_frame: int | None = None) -> np.ndarray:
        """One frame from a validated drive (`head.driver.drive(...)`): any FrameOutput; with `reference_frame`,
        the frame composited into that video frame's reference picture (uint8 only)."""
        if reference_frame is None:
            return self.frame_renderer.render(drive, output)
        if output == "semantic":
            raise RenderError("the semantic pass is the bare head's; it takes no reference_frame")
        check_composited_output(self.compositor, output)
        return self.compositor.frame(self.frame_renderer.draw(self.frame_renderer.prepare(drive), "rgba_float"),
                                     reference_frame)

    def render_params(self, expression=None, jaw_pose=None, neck_pose=None, eye_pose=None, head_rotation=None,
                      head_translation=None, output: FrameOutput = "uint8") -> np.ndarray:
        """One frame of a FLAME speaker from explicit FLAME parameters and head pose (a face tracker's)."""
        check_drive_rig(self.driver.rig, FLAME_RIG, "use render_blendshapes()")
        return self.render(self.driver.drive(expression, jaw_pose, neck_pose, eye_pose, head_rotation,
                                             head_translation), output)

    def render_blendshapes(self, weights=None, head_pose=None, output: FrameOutput = "uint8") -> np.ndarray:
        """One frame of an ARKit speaker (docs/import.md): `weights` a {name: weight} dict of ARKit blendshapes
        (names left out are 0) or a [52] array; `head_pose` a HeadPose or [6] array (None: rest)."""
        check_drive_rig(self.driver.rig, ARKIT_RIG, "use render_params() or audio")
        return self.render(self.driver.drive(weights, head_pose), output)

    def live(self, *, lookahead_ms: float = 160.0, paced: bool = True, context_ms: float = 1000.0,
             output: FrameOutput | None = "uint8", audio_rate: int | None = None, idle=None,
             max_queued_s: float = 120.0, min_batch_frames: int = 1, stream_delay_ms: float | None = None):
        """A live session (runtime/live.py, docs/live.md): push audio chunks as they arrive, read each frame as
        soon as its audio plus `lookahead_ms` is in. `output` None: drives only (the driver alone, no pixels).
        `stream_delay_ms`: which of the translator's streams to run (80: a trained speaker's short one, cheaper
        below 160 ms of lookahead and less accurate; docs/live.md, "A stream for a short lookahead")."""
        from .live import LiveSession

        return LiveSession(self, lookahead_ms=lookahead_ms, paced=paced, context_ms=context_ms, output=output,
                           audio_rate=audio_rate, idle=idle, max_queued_s=max_queued_s,
                           min_batch_frames=min_batch_frames, stream_delay_ms=stream_delay_ms)

    def write_video(self, path: str | os.PathLike | VideoPlan, audio: AudioSource | None = None,
                    sample_rate: int | None = None, head_pose: HeadPoseSource = None, progress: bool = False,
                    on_frame: Callable[[np.ndarray], None] | None = None, *, alpha: bool | None = None,
                    codec: str | None = None, crf: int | None = None, preset: str | None = None,
                    container: str | None = None, motion: MotionSource = None, fps: float | None = None) -> Path:
        """Render and write a video with the audio muxed in (`on_frame` sees each frame); returns the path.

        `path` is a file name (the container from its extension or `container`; docs/video.md lists the formats)
        or a VideoPlan (`plan_video`), checked before the first frame is rendered (VideoError). A speaker with a
        translator renders `audio` through it; given a `motion`, or without a translator or audio, it plays the
        motion (None: the bundle's own) and muxes `audio` if given. `fps`: frames per second of the video (None:
        the speaker's; another rate samples the drives at its frame times, runtime/playback.py)."""
        plan = OutputView(self.camera, self.compositor is not None).video_plan(path, alpha=alpha, codec=codec, crf=crf,
                                                                              preset=preset, container=container)
        output = "rgba" if plan.alpha else "uint8"
        play = playback(self, audio, sample_rate, motion=motion)
        frames, total = video_frames(self, play, output, head_pose, fps)
        # closing: a failed write stops the frame loop's worker threads at once, not when the generator is collected
        with closing(frames), VideoWriter(plan.path, fps or self.fps, plan.size, audio=play.samples,
                                          sample_rate=self.sample_rate, plan=plan) as out:
            write_frames(out, frames, total, pipelined=self.backend_settings.pipeline is not False,
                         progress=progress, on_frame=on_frame)
        return plan.path

    def close(self) -> None:
        """Free the splatter (its GL objects)."""
        self.frame_renderer.release()

    def __enter__(self) -> TalkingHead:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["TalkingHead", "FrameOutput", "HeadPoseSource"]
