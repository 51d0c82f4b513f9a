"""The embedding API: load a bundle, turn audio or explicit FLAME parameters into frames, write a video.

    head = TalkingHead("speaker.gtb", resolution=(512, 512))
    for frame in head.frames("speech.wav"):      # uint8 [H, W, 3], one per video frame, streamed
        ...
    head.write_video("talk.mp4", "speech.wav")   # audio muxed in
    head.write_video("talk.webm", "speech.wav", alpha=True)   # with an alpha channel, for overlays
"""

from __future__ import annotations

import os
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Literal

import numpy as np

from gaussiantalker.sdk.audio import load_audio, prepare_audio
from gaussiantalker.sdk.bundle import Bundle
from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.config import SpeakerConfig
from gaussiantalker.sdk.drive import FrameDrive, HeadPose, pose_track_frame
from gaussiantalker.sdk.errors import AudioError, BundleError, RenderError
from gaussiantalker.sdk.render_settings import RenderSettings
from gaussiantalker.sdk.scene import Scene, SceneError, SceneGuard
from gaussiantalker.sdk.video import VideoWriter
from gaussiantalker.sdk.video_formats import plan_video

from .graphs import GraphBackend, OnnxRuntimeBackend
from .splatter import GLSplatter, PreparedSplats
from .translate import SILENCE_GATE_DBFS, iter_translate

AudioSource = str | os.PathLike | np.ndarray
# Per-stage timings kept per TalkingHead: at most this many recent calls (then trimmed to the newest half), so a
# long-running head's bookkeeping does not grow with the number of frames it has rendered.
MAX_TIMINGS_PER_STAGE = 10_000
HeadPoseSource = Callable[[int], HeadPose] | np.ndarray | HeadPose | None
# What a frame is returned as: "uint8" [H, W, 3] (converted once, at the end), "float" float32 [H, W, 3]
# (C + T * background, unclamped), or "rgba" uint8 [H, W, 4]: straight colour and coverage 1 - T, from the same
# draw without the background (for overlays and videos with alpha; `sdk.image.straight_rgba`).
FrameOutput = Literal["uint8", "float", "rgba"]


def _render_settings(bundle: Bundle, **overrides) -> RenderSettings:
    """The bundle's stored runtime defaults (BundleError if damaged) with the app's overrides (None: keep the
    default; RenderError if bad)."""
    try:
        defaults = RenderSettings.from_dict(bundle.manifest.get("runtime_defaults", {}))
    except (TypeError, ValueError) as exc:
        raise BundleError(f"{bundle.path}: manifest 'runtime_defaults' is invalid: {exc}") from None
    try:
        return defaults.with_overrides(**overrides)
    except (TypeError, ValueError) as exc:
        raise RenderError(str(exc)) from None


class TalkingHead:
    """A loaded speaker bundle plus an OpenGL splatter: audio or FLAME parameters in, frames out."""

    def __init__(self, bundle: str | os.PathLike | Bundle, *, resolution: tuple[int, int] | None = None,
                 camera: Camera | None = None, background=None, threads: int | None = None,
                 gl_context=None, silence_gate_dbfs: float | None = SILENCE_GATE_DBFS,
                 render_scale: float | None = None, render_target: str | None = None,
                 sort_interval: int | None = None, sort_key_bits: int | None = None) -> None:
        """`silence_gate_dbfs`: audio windows quieter than this (RMS, dBFS) fade to the neutral face (None: off).
        `render_scale` (draw at this fraction of the size, then upscale), `render_target` ("float32", "float16",
        "uint8" framebuffer), `sort_interval` (depth-sort every k-th frame) and `sort_key_bits` (32 or 16) trade
        accuracy for speed (`RenderSettings`, docs/precision.md); None takes the bundle's preset defaults (the
        contract's full-size float32 frame, sorted every frame on exact depth, for bundles without a preset)."""
        self.bundle = bundle if isinstance(bundle, Bundle) else Bundle(bundle)
        manifest = self.bundle.manifest
        self.render_settings = _render_settings(self.bundle, render_scale=render_scale, render_target=render_target,
                                                sort_interval=sort_interval, sort_key_bits=sort_key_bits)
        try:
            self.config = SpeakerConfig.from_dict(manifest["speaker"])
            self.config.check_timing()
        except (TypeError, ValueError, AttributeError) as exc:
            raise BundleError(f"{self.bundle.path}: manifest has no valid speaker config: {exc}") from exc
        self.graphs: GraphBackend = OnnxRuntimeBackend(self.bundle, threads=threads)
        self.pose_track = self.bundle.buffer("pose_track") if self.bundle.has_buffer("pose_track") else None
        self.camera = camera or Camera.from_dict(manifest["camera"])
        if resolution is not None:
            self.camera = self.camera.resized(*resolution)
        self.background = np.asarray(background if background is not None else manifest.get("background", (1, 1, 1)),
                                     dtype=np.float32).reshape(3)
        self.scene, self.scene_guard = self._scene()
        if self.scene_guard is not None:
            self.scene_guard.check_camera(self.camera)
        self.splatter = GLSplatter(gl_context, settings=self.render_settings)
        self.timings: dict[str, list[float]] = defaultdict(list)
        self.silence_gate_dbfs = silence_gate_dbfs

    def _scene(self) -> tuple[Scene | None, SceneGuard | None]:
        """The scene the bundle was specialised for (docs/scene.md) and its range checks; (None, None) if none."""
        data = self.bundle.manifest.get("scene")
        if data is None:
            return None, None
        try:
            scene = Scene.from_dict(data)
            return scene, SceneGuard(scene, self.config.n_expr)
        except (SceneError, TypeError, ValueError, AttributeError) as exc:
            raise BundleError(f"{self.bundle.path}: manifest 'scene' is invalid: {exc}") from None

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
            return load_audio(audio, self.config.sample_rate)
        if sample_rate is None:
            raise AudioError("an audio array needs its sample_rate")
        return prepare_audio(audio, sample_rate, self.config.sample_rate)

    def _run_translator(self, chunk: np.ndarray) -> dict:
        """One translator window through the graph (timed)."""
        if not self.has_translator:
            raise BundleError(f"{self.bundle.path}: this bundle was specialised for a flame-driven scene and has no "
                              "translator graph, so it cannot turn audio into frames: drive it with render_params() "
                              "or render(), or re-export it with an audio-driven scene (or without --scene)")
        start = time.perf_counter()
        out = self.graphs.run("translator", {"audio": chunk[None]})
        self._record("translator", time.perf_counter() - start)
        return out

    def translate_blocks(self, audio: np.ndarray) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """Audio (speaker rate, mono float32) -> (expression, jaw pose) blocks in frame order, one window at a time."""
        return iter_translate(self._run_translator, audio, self.config.samples_per_frame,
                              silence_gate_dbfs=self.silence_gate_dbfs)

    def translate(self, audio: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Audio (speaker rate, mono float32) -> expression [T, n_expr], jaw pose [T, 3] via the translator graph."""
        blocks = list(self.translate_blocks(audio))
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
    def gaussians(self, drive: FrameDrive) -> dict[str, np.ndarray]:
        """Run the deformation graph: world-space means, cov3d, rgb, opacity for one frame."""
        start = time.perf_counter()
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

    def render(self, drive: FrameDrive, output: FrameOutput = "uint8") -> np.ndarray:
        """One frame from validated drive parameters: uint8 [H, W, 3] (float32 with output="float", uint8
        [H, W, 4] with output="rgba")."""
        return self.draw(self.prepare(drive), output)

    def render_params(self, expression=None, jaw_pose=None, neck_pose=None, eye_pose=None,
                      head_rotation=None, head_translation=None, output: FrameOutput = "uint8") -> np.ndarray:
        """One frame from explicit FLAME parameters and head pose (for apps driven by a face tracker)."""
        drive = FrameDrive.make(self.config.n_expr, expression, jaw_pose, neck_pose, eye_pose,
                                HeadPose.make(head_rotation, head_translation))
        return self.render(drive, output)

    def drives(self, audio: AudioSource, sample_rate: int | None = None,
               head_pose: HeadPoseSource = None) -> Iterator[FrameDrive]:
        """Per-frame drive parameters for an audio clip (translator output + head pose), translated per window."""
        index = 0
        for expression, jaw in self.translate_blocks(self.load_audio(audio, sample_rate)):
            for row in range(expression.shape[0]):
                yield FrameDrive.make(self.config.n_expr, expression[row], jaw[row],
                                      head_pose=self.head_pose(index, head_pose))
                index += 1

    def frames(self, audio: AudioSource, sample_rate: int | None = None, head_pose: HeadPoseSource = None,
               output: FrameOutput = "uint8") -> Iterator[np.ndarray]:
        """Frames for an audio clip at the speaker's fps, yielded one at a time (never all held in memory).

        Frame t+1 is prepared (deformation graph, depth sort) on a worker thread while the GL splatter draws
        frame t (onnxruntime and numpy release the GIL), so the two stages overlap instead of adding up.
        """
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="gt-deform") as pool:
            pending = None
            for drive in self.drives(audio, sample_rate, head_pose):
                upcoming = pool.submit(self.prepare, drive)
                if pending is not None:
                    yield self.draw(pending.result(), output)
                pending = upcoming
            if pending is not None:
                yield self.draw(pending.result(), output)

    def frame_count(self, samples: int) -> int:
        """Video frames for `samples` audio samples: the last partial frame counts (audio is zero-padded)."""
        return -(-samples // self.config.samples_per_frame)

    def write_video(self, path: str | os.PathLike, audio: AudioSource, sample_rate: int | None = None,
                    head_pose: HeadPoseSource = None, progress: bool = False,
                    on_frame: Callable[[np.ndarray], None] | None = None, *, alpha: bool = False,
                    codec: str | None = None, crf: int | None = None, preset: str | None = None,
                    container: str | None = None) -> Path:
        """Render the clip and write a video with the audio muxed in (`on_frame` sees each frame); returns the path.

        The container comes from the extension (or `container`): mp4, mov, webm, mkv, gif, or an image sequence
        such as "frames/%05d.png"; `alpha=True` writes coverage as an alpha channel (webm, mov with
        codec="prores", mkv, png). Everything about the output is checked before the first frame is rendered
        (`sdk.video_formats.plan_video`, VideoError); docs/video.md lists the formats.
        """
        from tqdm import tqdm

        plan = plan_video(path, (self.camera.width, self.camera.height), alpha=alpha, codec=codec, crf=crf,
                          preset=preset, container=container)
        samples = self.load_audio(audio, sample_rate)
        total = self.frame_count(samples.shape[0])
        with VideoWriter(path, self.config.fps, plan.size, audio=samples, sample_rate=self.config.sample_rate,
                         plan=plan) as out:
            frames = self.frames(samples, self.config.sample_rate, head_pose, output="rgba" if alpha else "uint8")
            for frame in tqdm(frames, total=total, unit="frame", disable=not progress, desc="rendering"):
                out.write(frame)
                if on_frame is not None:
                    on_frame(frame)
        return plan.path

    def close(self) -> None:
        self.splatter.release()

    def __enter__(self) -> TalkingHead:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["TalkingHead", "FrameOutput", "HeadPoseSource"]
