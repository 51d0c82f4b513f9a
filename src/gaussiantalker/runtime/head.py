"""The embedding API: load a bundle, turn audio or explicit FLAME parameters into frames, write a video.

    head = TalkingHead("speaker.gtb", resolution=(512, 512))
    for frame in head.frames("speech.wav"):      # uint8 [H, W, 3], one per video frame, streamed
        ...
    head.write_video("talk.mp4", "speech.wav")   # audio muxed in
    head.write_video("talk.webm", "speech.wav", alpha=True)   # with an alpha channel, for overlays

Settings come in groups, as onnxruntime takes SessionOptions (runtime/settings.py, docs/embedding.md); the plain
keywords above are shortcuts for their fields:

    head = TalkingHead("speaker.gtb", output=OutputSettings(resolution=(512, 512)),
                       render=RenderSettings(render_scale=0.5), backend=BackendSettings("mnn", threads=2))

A bundle with a reference clip composites every frame into the speaker's own video (docs/compositing.md):
the output has the clip's size and camera, and the head follows the clip's pose track; `composite=False` gives
the bare head.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from contextlib import closing
from pathlib import Path
from typing import Literal

import numpy as np

from gaussiantalker.sdk.audio import load_audio, prepare_audio
from gaussiantalker.sdk.bundle import Bundle
from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.config import SpeakerConfig
from gaussiantalker.sdk.drive import BlendshapeDrive, FrameDrive, HeadPose, pose_track_frame, track_row
from gaussiantalker.sdk.errors import AudioError, BundleError, DriveError, RenderError, VideoError
from gaussiantalker.sdk.flame_motion import FlameMotion
from gaussiantalker.sdk.motion import MotionTrack
from gaussiantalker.sdk.reference_clip import ReferenceClip
from gaussiantalker.sdk.render_settings import RenderSettings
from gaussiantalker.sdk.rig import ARKIT_BLENDSHAPES, ARKIT_RIG, FLAME_RIG, ArkitRig, check_drive_rig, rig_kind
from gaussiantalker.sdk.scene import Scene, SceneError, SceneGuard
from gaussiantalker.sdk.video import VideoWriter
from gaussiantalker.sdk.video_formats import VideoPlan

from .backend import GraphBackend, open_backend
from .composite import Inpainter, composite, graph_inpainter, opencv_fallback
from .motions import MotionSource, arkit_motion, flame_motion
from .output import COMPOSITE_ALPHA_MESSAGE, OutputView, output_view
from .pipeline import Ahead, Sink, in_order
from .renderer import make_splatter
from .semantic import Regions
from .settings import BackendSettings, OutputSettings, merged_backend, merged_output, merged_render
from .splatter import PreparedSplats
from .translate import SILENCE_GATE_DBFS, blendshape_params, iter_translate

AudioSource = str | os.PathLike | np.ndarray
# Per-stage timings kept per TalkingHead: at most this many recent calls (then trimmed to the newest half), so a
# long-running head's bookkeeping does not grow with the number of frames it has rendered.
MAX_TIMINGS_PER_STAGE = 10_000
# Pipelined frame loops (runtime/pipeline.py): frames prepared (deformed and sorted) ahead of the draw, and
# frames queued for the encoder. Each prepared frame holds its sorted rows (52 bytes a Gaussian), each queued frame
# its pixels, so these bound the memory the overlap costs.
PREPARED_AHEAD = 2
ENCODE_AHEAD = 2
HeadPoseSource = Callable[[int], HeadPose] | np.ndarray | HeadPose | None
# What a frame is returned as: "uint8" [H, W, 3] (converted once, at the end; the composited frame when
# compositing), "float" float32 [H, W, 3] (C + T * background, unclamped), "rgba" uint8 [H, W, 4]: straight colour
# and coverage 1 - T, from the same draw without the background (for overlays and videos with alpha;
# `sdk.image.straight_rgba`), "rgba_float" float32 [H, W, 4]: premultiplied (C, 1 - T) as splatted, or (render
# only) "semantic" uint8 [H, W, 3]: each Gaussian in its region's colour over black (`TalkingHead.regions`).
FrameOutput = Literal["uint8", "float", "rgba", "rgba_float", "semantic"]


def _render_settings(bundle: Bundle, render: RenderSettings | None = None, threads: int | None = None,
                     threads_label: str = "threads", **shortcuts) -> RenderSettings:
    """The render settings: `render` (None: the bundle's stored runtime defaults, BundleError if damaged) with the
    app's shortcut keywords (None: keep the value; SettingsError if bad or given twice)."""
    try:
        preset = RenderSettings.from_dict(bundle.manifest.get("runtime_defaults", {}))
    except (TypeError, ValueError) as exc:
        raise BundleError(f"{bundle.path}: manifest 'runtime_defaults' is invalid: {exc}") from None
    return merged_render(preset, render, threads, threads_label, **shortcuts)


class TalkingHead:
    """A loaded speaker bundle plus a splatter (OpenGL or the CPU tile splatter): audio or FLAME parameters in,
    frames out."""

    def __init__(self, bundle: str | os.PathLike | Bundle, *, render: RenderSettings | None = None,
                 output: OutputSettings | None = None, backend: str | BackendSettings = "onnxruntime",
                 resolution: tuple[int, int] | None = None, camera: Camera | None = None, background=None,
                 composite: bool | None = None, threads: int | None = None, shader_target: str | None = None,
                 renderer: str | None = None, render_scale: float | None = None, render_target: str | None = None,
                 sort_interval: int | None = None, sort_key_bits: int | None = None, pipeline: bool | None = None,
                 gl_context=None, silence_gate_dbfs: float | None = SILENCE_GATE_DBFS) -> None:
        """Settings come in three groups (docs/embedding.md), each None for the bundle's defaults:
        `render` (RenderSettings: render scale, framebuffer precision, sort interval and key bits, graph threads;
        None: the bundle's preset, else the contract's full-size float32 frame sorted every frame on exact depth;
        docs/precision.md), `output` (OutputSettings: resolution, camera, background, composite; compositing
        defaults to whether the bundle has a reference clip, docs/compositing.md) and `backend` (a name,
        "onnxruntime" or "mnn" (docs/mnn.md), or BackendSettings: name, threads, shader_target, renderer).

        The keywords resolution, camera, background, composite (output), threads, shader_target, renderer (backend:
        "gl", "cpu" or "auto", docs/embedding.md; `head.renderer` says which one draws), pipeline (backend: the
        frame loops overlap neighbouring frames' stages on worker threads, None: on; docs/speed.md) and
        render_scale, render_target, sort_interval, sort_key_bits (render) are shortcuts for a group's field: one
        given both ways with two values is a SettingsError naming both. `gl_context`: a moderngl context to draw
        in (None: a headless one of its own). `silence_gate_dbfs`: audio windows quieter than this (RMS, dBFS) fade
        to the neutral face (None: off)."""
        self.bundle = bundle if isinstance(bundle, Bundle) else Bundle(bundle)
        manifest = self.bundle.manifest
        self.output_settings = merged_output(output, resolution=resolution, camera=camera, background=background,
                                             composite=composite)
        backend_settings = merged_backend(backend, threads=threads, shader_target=shader_target, renderer=renderer,
                                          pipeline=pipeline)
        threads_label = "backend.threads" if isinstance(backend, BackendSettings) and threads is None else "threads"
        self.render_settings = _render_settings(self.bundle, render, backend_settings.threads, threads_label,
                                                render_scale=render_scale, render_target=render_target,
                                                sort_interval=sort_interval, sort_key_bits=sort_key_bits)
        self.backend_settings = dataclasses.replace(backend_settings, threads=self.render_settings.graph_threads)
        self.rig, self.config, self.arkit = self._rig(manifest)
        self.graphs: GraphBackend = open_backend(self.bundle, self.backend_settings.name,
                                                 threads=self.backend_settings.threads)
        self.pose_track = self.bundle.buffer("pose_track") if self.bundle.has_buffer("pose_track") else None
        settings = self.output_settings
        view = output_view(self.bundle, settings)
        self.camera, self.composite = view.camera, view.composite
        background = settings.background
        if background is None:  # the bundle's: 3 numbers finite in float32 (docs/untrusted-input.md, "Bundles")
            background = manifest.get("background", (1, 1, 1))
            if not (isinstance(background, list | tuple) and len(background) == 3 and all(
                    isinstance(c, int | float) and not isinstance(c, bool) and abs(c) <= float(np.finfo(np.float32).max)
                    for c in background)):
                raise BundleError(f"{self.bundle.path}: manifest 'background' must be 3 finite numbers (RGB), got "
                                  f"{repr(background)[:80]}")
        self.background = np.asarray(background, dtype=np.float32).reshape(3)
        self.reference, self._inpaint = self._reference(settings.resolution)
        self.scene, self.scene_guard = self._scene()
        if self.scene_guard is not None:
            self.scene_guard.check_camera(self.camera)
        self.splatter, self.renderer = make_splatter(self.backend_settings.renderer, gl_context=gl_context,
                                                     settings=self.render_settings,
                                                     shader_target=self.backend_settings.shader_target)
        self.timings: dict[str, list[float]] = defaultdict(list)
        self.silence_gate_dbfs = silence_gate_dbfs
        # Read at load like every entry a frame may need, so a damaged one fails here, not mid-video.
        self._regions = Regions(self.bundle) if "regions" in manifest else None

    def _rig(self, manifest: dict) -> tuple[str, SpeakerConfig | None, ArkitRig | None]:
        """(rig kind, FLAME speaker config or None, ARKit rig or None) from the manifest, checked."""
        try:
            kind = rig_kind(manifest)
            if kind == ARKIT_RIG:
                return kind, None, ArkitRig.from_dict(manifest["rig"])
        except (TypeError, ValueError) as exc:
            raise BundleError(f"{self.bundle.path}: manifest has no valid rig: {exc}") from exc
        try:
            config = SpeakerConfig.from_dict(manifest["speaker"])
            config.check_timing()
        except (TypeError, ValueError, AttributeError) as exc:
            raise BundleError(f"{self.bundle.path}: manifest has no valid speaker config: {exc}") from exc
        return kind, config, None

    @property
    def pipelined(self) -> bool:
        """Whether `frames`, `motion_frames` and `write_video` overlap neighbouring frames' stages on worker threads
        (runtime/pipeline.py); the frames are the same either way."""
        return self.backend_settings.pipeline is not False

    @property
    def fps(self) -> int:
        """Video frames per second of this speaker."""
        return self.arkit.fps if self.arkit is not None else self.config.fps

    @property
    def sample_rate(self) -> int:
        """Audio sample rate (Hz) this speaker's audio is resampled to."""
        return self.arkit.sample_rate if self.arkit is not None else self.config.sample_rate

    @property
    def motion_track(self) -> MotionTrack | FlameMotion | None:
        """The motion the bundle ships at the speaker's fps (an ARKit speaker's weights, an imported FLAME avatar's
        tracked parameters), None if it has none."""
        if not self.bundle.has_buffer("motion_track"):
            return None
        table = self.bundle.buffer("motion_track")
        return MotionTrack(table, self.fps) if self.rig == ARKIT_RIG else FlameMotion.from_table(table, self.fps)

    @classmethod
    def output_view(cls, bundle: str | os.PathLike | Bundle, output: OutputSettings | None = None, *,
                    resolution: tuple[int, int] | None = None, camera: Camera | None = None, background=None,
                    composite: bool | None = None) -> OutputView:
        """The camera and compositing a head with these output settings (or their shortcut keywords) would have,
        from the manifest alone: `.size`, `.composite`, `.plan_video(...)` check an output before the speaker is
        loaded."""
        bundle = bundle if isinstance(bundle, Bundle) else Bundle(bundle)
        return output_view(bundle, merged_output(output, resolution=resolution, camera=camera, background=background,
                                                 composite=composite))

    @property
    def frame_size(self) -> tuple[int, int]:
        """(width, height) of this head's frames."""
        return self.camera.width, self.camera.height

    def plan_video(self, path: str | os.PathLike, *, alpha: bool = False, codec: str | None = None,
                   crf: int | None = None, preset: str | None = None, container: str | None = None) -> VideoPlan:
        """The checked plan for writing this head's frames to `path` (`write_video` takes it): container from the
        extension or `container`, codec, crf, preset; VideoError if it cannot work (docs/video.md), RenderError
        for alpha on composited frames."""
        return OutputView(self.camera, self.composite).plan_video(path, alpha=alpha, codec=codec, crf=crf,
                                                                  preset=preset, container=container)

    def _scene(self) -> tuple[Scene | None, SceneGuard | None]:
        """The scene the bundle was specialised for (docs/scene.md) and its range checks; (None, None) if none."""
        data = self.bundle.manifest.get("scene")
        if data is None:
            return None, None
        try:
            scene = Scene.from_dict(data)
            if self.config is None:
                raise SceneError("scenes are for FLAME speakers")
            return scene, SceneGuard(scene, self.config.n_expr)
        except (SceneError, TypeError, ValueError, AttributeError) as exc:
            raise BundleError(f"{self.bundle.path}: manifest 'scene' is invalid: {exc}") from None

    def _reference(self, resolution: tuple[int, int] | None) -> tuple[ReferenceClip | None, Inpainter | None]:
        """The bundle's reference clip (None if it has none) and, when compositing, F."""
        reference = ReferenceClip(self.bundle, resolution) if "reference" in self.bundle.manifest else None
        if not self.composite:
            return reference, None
        if self.pose_track is None or len(self.pose_track) != len(reference):
            raise BundleError(f"{self.bundle.path}: the reference clip has {len(reference)} frames but the pose "
                              f"track has {0 if self.pose_track is None else len(self.pose_track)} rows")
        inpaint = graph_inpainter(self.graphs.run) if "inpaint" in self.bundle.manifest["graphs"] else opencv_fallback
        return reference, inpaint

    @property
    def has_translator(self) -> bool:
        """Whether the bundle can turn audio into frames (a flame-driven scene's bundle has no translator graph)."""
        return "translator" in self.bundle.manifest["graphs"]

    def _record(self, stage: str, seconds: float) -> None:
        """Append a stage timing; past MAX_TIMINGS_PER_STAGE values only the newest half of that many are kept."""
        values = self.timings[stage]
        values.append(seconds)
        if len(values) > MAX_TIMINGS_PER_STAGE:
            del values[: len(values) - MAX_TIMINGS_PER_STAGE // 2]

    # -- audio -> drive ------------------------------------------------------------------------------
    def load_audio(self, audio: AudioSource, sample_rate: int | None = None) -> np.ndarray:
        """Any file or array -> mono float32 at the speaker's sample rate."""
        if isinstance(audio, (str, os.PathLike)):
            return load_audio(audio, self.sample_rate)
        if sample_rate is None:
            raise AudioError("an audio array needs its sample_rate")
        return prepare_audio(audio, sample_rate, self.sample_rate)

    def run_translator(self, chunk: np.ndarray) -> dict:
        """One translator window through the bundle's translator graph (timed): mono float32 audio at the speaker's
        rate -> the graph's outputs by name. `translate` and live sessions window long audio through it."""
        if not self.has_translator:
            why = ("was specialised for a flame-driven scene" if self.scene is not None else
                   "holds an imported avatar without an audio model")
            raise BundleError(f"{self.bundle.path}: this bundle {why} and has no translator graph, so it cannot turn "
                              "audio into frames: drive it with render_params(), render() or motion_frames() (a "
                              "motion file), or re-export it without --scene / attach an audio model "
                              "(gt-import voice CHECKPOINT --bundle BUNDLE; docs/voice.md)")
        start = time.perf_counter()
        out = self.graphs.run("translator", {"audio": chunk[None]})
        self._record("translator", time.perf_counter() - start)
        return out

    def translate_blocks(self, audio: np.ndarray) -> Iterator:
        """Audio (speaker rate, mono float32) -> blocks in frame order, one window at a time: (expression, jaw pose)
        for a FLAME speaker, ARKit weights [n, 52] for an ARKit speaker with an audio model (docs/import.md)."""
        if self.rig == ARKIT_RIG:
            if not self.has_translator:
                raise DriveError(f"{self.bundle.path}: this ARKit speaker has no audio model attached, so it cannot "
                                 "turn audio into frames: drive it with render_blendshapes(), motion_frames() or a "
                                 "motion file, or attach one (gt-import voice CHECKPOINT --bundle BUNDLE; "
                                 "docs/voice.md)")
            return iter_translate(self.run_translator, audio, self.sample_rate / self.fps,
                                  silence_gate_dbfs=self.silence_gate_dbfs, params_of=blendshape_params)
        return iter_translate(self.run_translator, audio, self.config.samples_per_frame,
                              silence_gate_dbfs=self.silence_gate_dbfs)

    def translate(self, audio: np.ndarray) -> tuple[np.ndarray, np.ndarray] | np.ndarray:
        """Audio (speaker rate, mono float32) -> expression [T, n_expr], jaw pose [T, 3] via the translator graph
        (an ARKit speaker: its audio model's weights [T, 52])."""
        blocks = list(self.translate_blocks(audio))
        if self.rig == ARKIT_RIG:
            return np.concatenate(blocks)
        return np.concatenate([b[0] for b in blocks]), np.concatenate([b[1] for b in blocks])

    def head_pose(self, index: int, source: HeadPoseSource = None) -> HeadPose:
        """Head pose of frame `index`: the app's (callable, [T, 6] array or fixed pose) or the pose track's."""
        if isinstance(source, HeadPose):
            return source
        if callable(source):
            return source(index)
        track = source if source is not None else self.pose_track
        if track is None:
            return HeadPose.make()
        return pose_track_frame(np.asarray(track, dtype=np.float32).reshape(-1, 6), index)

    # -- drive -> frame ------------------------------------------------------------------------------
    def gaussians(self, drive: FrameDrive | BlendshapeDrive) -> dict[str, np.ndarray]:
        """Run the deformation graph: world-space means, cov3d, rgb, opacity for one frame."""
        start = time.perf_counter()
        check_drive_rig(self.rig, drive.rig)
        inputs = drive.graph_inputs()
        if self.scene_guard is not None:
            self.scene_guard.check_drive(drive.expression, drive.flame_pose, drive.head_translation)
        inputs["camera_center"] = self.camera.center.astype(np.float32)[None]
        out = self.graphs.run("deform", inputs)
        self._record("deformation", time.perf_counter() - start)
        return {"means": out["means"][0], "cov3d": out["cov3d"][0], "rgb": out["rgb"][0], "opacity": out["opacity"]}

    def prepare(self, drive: FrameDrive) -> PreparedSplats:
        """Everything of a frame that needs no GL: deformation graph, packing, depth sort (thread-safe)."""
        g = self.gaussians(drive)
        return self.splatter.prepare(g["means"], g["cov3d"], g["rgb"], g["opacity"], self.camera)

    def draw(self, prepared: PreparedSplats, output: FrameOutput = "uint8") -> np.ndarray:
        """The GL part of a frame: upload, splat, read back."""
        frame = self.splatter.draw(prepared, self.background, output=output)
        for stage, seconds in self.splatter.last_timings.items():
            self._record(stage, seconds)
        return frame

    def render(self, drive: FrameDrive, output: FrameOutput = "uint8", reference_frame: int | None = None
               ) -> np.ndarray:
        """One frame from validated drive parameters: uint8 [H, W, 3] (float32 with output="float", uint8
        [H, W, 4] with output="rgba", float32 [H, W, 4] with output="rgba_float"); with `reference_frame`, the
        frame composited into that video frame's reference picture (uint8 only)."""
        if output == "semantic":
            if reference_frame is not None:
                raise RenderError("the semantic pass is the bare head's; it takes no reference_frame")
            g = self.gaussians(drive)
            return self._draw_in_colors(g, self.regions.gaussian_colors(g["opacity"].shape[0]), "uint8")
        if reference_frame is None:
            return self.draw(self.prepare(drive), output)
        self._check_composite_output(output)
        return self.composite_frame(self.draw(self.prepare(drive), "rgba_float"), reference_frame)

    @property
    def regions(self) -> Regions:
        """The bundle's semantic regions: `names`, `colors` [R, 3] (the semantic pass's), per-Gaussian `ids`."""
        if self._regions is None:
            raise BundleError(f"{self.bundle.path}: bundle has no semantic regions (manifest 'regions'); re-export "
                              "a speaker whose FLAME model labels its triangles")
        return self._regions

    def region_weights(self, drive: FrameDrive) -> np.ndarray:
        """Per-region coverage float32 [H, W, R]: the summed blend weight of each region's Gaussians at every
        pixel (the regions sum to the frame's coverage 1 - T), a soft mask per region. Costs ceil(R / 3) draws."""
        g = self.gaussians(drive)
        count, names = g["opacity"].shape[0], self.regions.names
        passes = []
        for first in range(0, len(names), 3):
            passes.append(self._draw_in_colors(g, self.regions.one_hot(count, first), "float"))
        return np.concatenate(passes, axis=-1)[..., : len(names)]

    def _draw_in_colors(self, g: dict[str, np.ndarray], colors: np.ndarray, output: FrameOutput) -> np.ndarray:
        """A frame's Gaussians `g` drawn with these colours [N, 3] instead of their own, over black."""
        prepared = self.splatter.prepare(g["means"], g["cov3d"], colors, g["opacity"], self.camera)
        return self.splatter.draw(prepared, (0.0, 0.0, 0.0), output=output)

    def _check_composite_output(self, output: str) -> None:
        if not self.composite:
            raise RenderError("compositing is off for this head (no reference clip, or composite=False)")
        if output != "uint8":
            raise RenderError(f"composited frames are uint8 RGB; output={output!r} needs the bare head: "
                              "TalkingHead(..., composite=False)")

    def composite_frame(self, head: np.ndarray, index: int) -> np.ndarray:
        """Video frame `index` composited: the premultiplied render `head` [H, W, 4] (output="rgba_float") into
        the reference picture the clip shows at that frame (forth and back), uint8 [H, W, 3]."""
        return self._composite(head, *self._reference_picture(index))

    def render_params(self, expression=None, jaw_pose=None, neck_pose=None, eye_pose=None,
                      head_rotation=None, head_translation=None, output: FrameOutput = "uint8") -> np.ndarray:
        """One frame from explicit FLAME parameters and head pose (for apps driven by a face tracker)."""
        check_drive_rig(self.rig, FLAME_RIG, "use render_blendshapes()")
        drive = FrameDrive.make(self.config.n_expr, expression, jaw_pose, neck_pose, eye_pose,
                                HeadPose.make(head_rotation, head_translation))
        return self.render(drive, output)

    # -- ARKit speakers ------------------------------------------------------------------------------
    def render_blendshapes(self, weights=None, head_pose: HeadPose | np.ndarray | None = None,
                           output: FrameOutput = "uint8") -> np.ndarray:
        """One frame of an ARKit speaker (docs/import.md): `weights` a {name: weight} dict of ARKit blendshapes
        (names left out are 0) or a [52] array in ARKIT_BLENDSHAPES order; `head_pose` a HeadPose or [6] array
        (rotation about the head bone's pivot, translation; None: rest); every output of `render`."""
        return self.render(self.blendshape_drive(weights, head_pose), output)

    def blendshape_drive(self, weights=None, head_pose: HeadPose | np.ndarray | None = None) -> BlendshapeDrive:
        """The validated drive of `render_blendshapes`'s arguments (DriveError for a FLAME speaker)."""
        check_drive_rig(self.rig, ARKIT_RIG, "use render_params() or audio")
        if head_pose is not None and not isinstance(head_pose, HeadPose):
            row = np.asarray(head_pose, dtype=np.float64)
            if row.shape != (6,):
                raise DriveError(f"head_pose must be a HeadPose or [6] (rotation, translation), got shape "
                                 f"{tuple(row.shape)}")
            head_pose = HeadPose.make(row[:3], row[3:])
        if weights is not None and not isinstance(weights, dict) and self.arkit.blendshapes != ARKIT_BLENDSHAPES:
            weights = dict(zip(ARKIT_BLENDSHAPES, np.asarray(weights).reshape(-1), strict=True))
        return BlendshapeDrive.make(weights, head_pose, self.arkit.blendshapes)

    def motion(self, motion: MotionSource = None) -> MotionTrack | FlameMotion:
        """A motion at this speaker's fps (runtime/motions.py): for an ARKit speaker a motion file (LAM's JSON
        kinds), a MotionTrack or [T, 52] weights; for a FLAME speaker a FLAME motion npz (GaussianAvatars'
        flame_param.npz keys), a FlameMotion or a [T, n_expr + 18] table; None: the motion the bundle ships."""
        where = str(self.bundle.path)
        if self.rig == ARKIT_RIG:
            return arkit_motion(motion, self.motion_track, self.fps, where)
        return flame_motion(motion, self.motion_track, self.fps, self.config.n_expr, where)

    def motion_drives(self, motion: MotionSource = None, head_pose: HeadPoseSource = None
                      ) -> Iterator[BlendshapeDrive | FrameDrive]:
        """One drive per frame of a motion (see `motion`). An ARKit speaker's head follows `head_pose` or the pose
        track; a FLAME motion carries its own head pose, which `head_pose` (if given) replaces."""
        track = self.motion(motion)
        if isinstance(track, FlameMotion):
            for index in range(len(track)):
                yield track.drive(index, None if head_pose is None else self.head_pose(index, head_pose))
            return
        for index, weights in enumerate(track.weights):
            yield self.blendshape_drive(weights, self.head_pose(index, head_pose))

    def motion_frames(self, motion: MotionSource = None, head_pose: HeadPoseSource = None,
                      output: FrameOutput = "uint8") -> Iterator[np.ndarray]:
        """Frames of a speaker playing a motion (see `motion`), one per motion frame, streamed and pipelined like
        `frames`."""
        yield from self._bare_frames(self.motion_drives(motion, head_pose), output)

    def drives(self, audio: AudioSource, sample_rate: int | None = None,
               head_pose: HeadPoseSource = None) -> Iterator[FrameDrive | BlendshapeDrive]:
        """Per-frame drive parameters for an audio clip (translator output + head pose), translated per window."""
        index = 0
        for block in self.translate_blocks(self.load_audio(audio, sample_rate)):
            if self.rig == ARKIT_RIG:
                for weights in block:
                    yield self.blendshape_drive(weights, self.head_pose(index, head_pose))
                    index += 1
                continue
            expression, jaw = block
            for row in range(expression.shape[0]):
                yield FrameDrive.make(self.config.n_expr, expression[row], jaw[row],
                                      head_pose=self.head_pose(index, head_pose))
                index += 1

    def frames(self, audio: AudioSource, sample_rate: int | None = None, head_pose: HeadPoseSource = None,
               output: FrameOutput = "uint8") -> Iterator[np.ndarray]:
        """Frames for an audio clip at the speaker's fps, yielded one at a time (never all held in memory).

        Pipelined (the default; `pipeline=False` turns it off, the frames are the same): the next frames are
        prepared (translator, deformation graph, depth sort) on a worker thread while this thread draws frame t
        (onnxruntime, numpy and the CPU splatter's kernels release the GIL), so the stages overlap instead of
        adding up (runtime/pipeline.py, docs/speed.md).
        When compositing, each frame goes into the reference clip's picture at the same index as its pose.
        """
        if not self.composite:
            yield from self._bare_frames(self.drives(audio, sample_rate, head_pose), output)
            return
        self._check_composite_output(output)
        if head_pose is not None:
            raise RenderError("a composited head follows the reference clip's pose track (any other pose "
                              "would misalign it with the clip); pass composite=False to set head_pose")
        yield from self._composited_frames(self.drives(audio, sample_rate))

    def _bare_frames(self, drives: Iterator[FrameDrive], output: FrameOutput) -> Iterator[np.ndarray]:
        """Two overlapping stages when pipelined: the next frames' drives, deformation and sort on a worker thread
        (up to PREPARED_AHEAD frames ahead) while this thread draws (a GL context is bound to the thread that
        made it)."""
        if not self.pipelined:
            for drive in drives:
                yield self.draw(self.prepare(drive), output)
            return
        with Ahead((self.prepare(drive) for drive in drives), PREPARED_AHEAD, "gt-prepare") as prepared:
            for splats in prepared:
                yield self.draw(splats, output)

    def _composited_frames(self, drives: Iterator[FrameDrive]) -> Iterator[np.ndarray]:
        """Three overlapping stages when pipelined: the next frames prepared with their reference pictures decoded,
        frame t drawn on this thread, frame t-1 composited (F and the blend), each on its own thread, so the
        composite costs no frame time when the machine has cores to spare."""
        prepared = (self._prepare_composited(drive, index) for index, drive in enumerate(drives))
        if not self.pipelined:
            for splats, picture, mask in prepared:
                yield self._composite(self.draw(splats, "rgba_float"), picture, mask)
            return
        with Ahead(prepared, PREPARED_AHEAD, "gt-prepare") as ahead:
            drawn = ((self.draw(splats, "rgba_float"), picture, mask) for splats, picture, mask in ahead)
            yield from in_order(self._composite, drawn, 1, "gt-composite")

    def _reference_picture(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """The reference frame and mask video frame `index` is composited into (the clip forth and back), timed."""
        start = time.perf_counter()
        row = track_row(len(self.reference), int(index))
        picture, mask = self.reference.frame(row), self.reference.mask(row)
        self._record("reference", time.perf_counter() - start)
        return picture, mask

    def _prepare_composited(self, drive: FrameDrive, index: int) -> tuple[PreparedSplats, np.ndarray, np.ndarray]:
        return (self.prepare(drive), *self._reference_picture(index))

    def _composite(self, head: np.ndarray, picture: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """The formula on the mask's crop (F and the blend), timed."""
        start = time.perf_counter()
        frame = composite(head, picture, mask, self._inpaint)
        self._record("composite", time.perf_counter() - start)
        return frame

    def live(self, *, lookahead_ms: float = 160.0, paced: bool = True, context_ms: float = 1000.0,
             output: FrameOutput | None = "uint8", audio_rate: int | None = None, idle=None,
             max_queued_s: float = 120.0):
        """A live session (runtime/live.py, docs/live.md): push audio chunks as they arrive, read each frame as
        soon as its audio plus `lookahead_ms` is in. `paced`: frames at the frame rate on the wall clock, idling
        when no audio is queued; False: as fast as they are ready. `output`: a FrameOutput, or None for drives
        only (no rendering). `audio_rate`: the rate of each LiveFrame's audio (None: the speaker's). `idle`: an
        IdleMotion (blinks, sway, ease). Sessions of one head share its weights and GL context; read each
        session's frames on the thread that made the head."""
        from .live import LiveSession

        return LiveSession(self, lookahead_ms=lookahead_ms, paced=paced, context_ms=context_ms, output=output,
                           audio_rate=audio_rate, idle=idle, max_queued_s=max_queued_s)

    def frame_count(self, samples: int) -> int:
        """Video frames for `samples` audio samples: the last partial frame counts (audio is zero-padded)."""
        if self.config is None:
            return math.ceil(samples * self.fps / self.sample_rate - 1e-9)
        return -(-samples // self.config.samples_per_frame)

    def write_video(self, path: str | os.PathLike | VideoPlan, audio: AudioSource | None = None,
                    sample_rate: int | None = None, head_pose: HeadPoseSource = None, progress: bool = False,
                    on_frame: Callable[[np.ndarray], None] | None = None, *, alpha: bool | None = None,
                    codec: str | None = None, crf: int | None = None, preset: str | None = None,
                    container: str | None = None, motion: MotionSource = None) -> Path:
        """Render the clip and write a video with the audio muxed in (`on_frame` sees each frame); returns the path.

        `path` is a file name or a VideoPlan (`plan_video`, `sdk.video_formats.plan_video`; it then says
        everything: no codec, crf, preset or container, and alpha only if the same). For a file name the container
        comes from the extension (or `container`): mp4, mov, webm, mkv, gif, or an image sequence such as
        "frames/%05d.png"; `alpha=True` writes coverage as an alpha channel (webm, mov with codec="prores", mkv,
        png). Everything about the output is checked before the first frame is rendered (VideoError);
        docs/video.md lists the formats.

        A speaker with a translator (a FLAME speaker's, an imported avatar's audio model) renders the audio through
        it; given a `motion` (see `TalkingHead.motion`), or without a translator or audio (then None: the bundle's
        own motion), it plays the motion and muxes `audio` if given.
        """
        from gaussiantalker.sdk.progress import progress_bar

        plan = self._video_plan(path, alpha=alpha, codec=codec, crf=crf, preset=preset, container=container)
        output = "rgba" if plan.alpha else "uint8"
        samples = None if audio is None else self.load_audio(audio, sample_rate)
        if self.rig == FLAME_RIG and samples is None and motion is None and self.has_translator \
                and self.motion_track is None:
            raise AudioError("this speaker's video needs audio (its translator turns speech into motion) or a motion")
        if motion is not None or samples is None or not self.has_translator:
            if self.composite:
                raise RenderError("a composited head follows the reference clip and its audio; play a motion with "
                                  "composite=False")
            track = self.motion(motion)
            frames, total = self.motion_frames(track, head_pose, output), len(track)
        else:
            frames = self.frames(samples, self.sample_rate, head_pose, output=output)
            total = self.frame_count(samples.shape[0])
        # closing: a failed write stops the frame loop's worker threads at once, not when the generator is collected
        with closing(frames), VideoWriter(plan.path, self.fps, plan.size, audio=samples,
                                          sample_rate=self.sample_rate, plan=plan) as out:
            if not self.pipelined:
                for frame in progress_bar(frames, total=total, unit="frame", disable=not progress, desc="rendering"):
                    out.write(frame)
                    if on_frame is not None:
                        on_frame(frame)
                return plan.path
            # Encoding on its own thread (PyAV releases the GIL) while the next frame is made; `on_frame` may
            # change its frame, so the encoder gets its own copy then.
            with Sink(out.write, ENCODE_AHEAD, "gt-encode") as encoder:
                for frame in progress_bar(frames, total=total, unit="frame", disable=not progress, desc="rendering"):
                    encoder.put(frame if on_frame is None else frame.copy())
                    if on_frame is not None:
                        on_frame(frame)
        return plan.path

    def _video_plan(self, path: str | os.PathLike | VideoPlan, *, alpha: bool | None, **options) -> VideoPlan:
        """`path` planned for this head's frames, or the given VideoPlan checked against them."""
        if not isinstance(path, VideoPlan):
            return self.plan_video(path, alpha=bool(alpha), **options)
        given = [f"{name}={value!r}" for name, value in options.items() if value is not None]
        if given:
            raise VideoError(f"a VideoPlan already sets the output; give it or {', '.join(given)}, not both")
        if alpha is not None and bool(alpha) != path.alpha:
            raise VideoError(f"alpha={alpha!r} but the VideoPlan has alpha={path.alpha}; give it once")
        if self.composite and path.alpha:
            raise RenderError(COMPOSITE_ALPHA_MESSAGE)
        if tuple(path.size) != self.frame_size:
            raise VideoError(f"the VideoPlan is for {path.size[0]}x{path.size[1]} frames but this head renders "
                             f"{self.frame_size[0]}x{self.frame_size[1]} (plan it with head.plan_video)")
        return path

    def close(self) -> None:
        self.splatter.release()

    def __enter__(self) -> TalkingHead:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["TalkingHead", "FrameOutput", "HeadPoseSource"]
