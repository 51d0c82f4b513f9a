"""The first stage of a frame's path (docs/embedding.md, "Stages"): a Driver turns audio or a motion into one drive
per frame, on the audio clock, for one rig. `FlameDriver` runs a FLAME speaker's translator (audio -> expression and
jaw) or plays a FLAME motion; `ArkitDriver` runs an ARKit avatar's audio model or plays an ARKit motion. Both own
their windowing (runtime/translate.py), their motion tracks and the head pose of each frame. A live session
without pixels is a Driver alone (runtime/live.py).
"""

from __future__ import annotations

import functools
import math
import os
import time
from collections.abc import Callable, Iterator

import numpy as np

from gaussiantalker.sdk.audio import load_audio, prepare_audio
from gaussiantalker.sdk.bundle import STREAM_GRAPH, STREAM_GRAPHS, Bundle
from gaussiantalker.sdk.config import SpeakerConfig
from gaussiantalker.sdk.drive import (
    BlendshapeDrive,
    FrameDrive,
    HeadPose,
    PoseTrack,
    blendshape_drive_of,
    blendshape_drive_rows,
    frame_drive_of,
    frame_drive_rows,
    pose_track_frame,
)
from gaussiantalker.sdk.errors import AudioError, BundleError, DriveError
from gaussiantalker.sdk.flame_motion import FlameMotion
from gaussiantalker.sdk.motion import MotionTrack
from gaussiantalker.sdk.rig import ARKIT_BLENDSHAPES, ARKIT_RIG, FLAME_RIG, ArkitRig

from .backend import GraphBackend
from .motions import MotionSource, arkit_motion, flame_motion
from .timings import Timings
from .translate import SILENCE_GATE_DBFS, blendshape_params, flame_params, iter_translate
from .translate_stream import StreamSpec, read_stream_spec

AudioSource = str | os.PathLike | np.ndarray
HeadPoseSource = Callable[[int], HeadPose] | np.ndarray | HeadPose | None
Drive = FrameDrive | BlendshapeDrive
ATTACH_VOICE_HINT = "attach one (gt-import voice CHECKPOINT --bundle BUNDLE; docs/voice.md)"


class Driver:
    """Audio or a motion in, one drive per frame out (the rig's own drive type). Subclasses say how a translator
    window's outputs become per-frame parameters and how parameters become a drive."""

    rig: str = ""

    def __init__(self, bundle: Bundle, graphs: GraphBackend, *, timings: Timings | None = None,
                 silence_gate_dbfs: float | None = SILENCE_GATE_DBFS) -> None:
        self.bundle, self.graphs = bundle, graphs
        self.timings = timings if timings is not None else Timings()
        self.silence_gate_dbfs = silence_gate_dbfs
        self.pose_track = bundle.buffer("pose_track") if bundle.has_buffer("pose_track") else None
        self._checked_track: tuple[object, PoseTrack] | None = None  # (pose_track, it checked once)

    # -- what each rig says --------------------------------------------------------------------------------------
    fps: int
    sample_rate: int
    samples_per_frame: float

    def params_of(self, out: dict, frames: int) -> np.ndarray:
        """A translator window's graph outputs -> per-frame parameters [frames, D]."""
        raise NotImplementedError

    def drive_from_params(self, params: np.ndarray, head_pose: HeadPose) -> Drive:
        """One frame's parameters [D] (a row of `params_of`) and head pose -> its drive."""
        raise NotImplementedError

    def clamp_params(self, params: np.ndarray) -> np.ndarray:
        """Parameters limited to the rig's range (made-up ones: a live session's idle motion added to speech)."""
        return params

    def motion(self, motion: MotionSource = None) -> MotionTrack | FlameMotion:
        """A motion at this speaker's fps (runtime/motions.py; None: the motion the bundle ships)."""
        raise NotImplementedError

    def motion_drives(self, motion: MotionSource = None, head_pose: HeadPoseSource = None) -> Iterator[Drive]:
        """One drive per frame of a motion (see `motion`)."""
        raise NotImplementedError

    def _no_translator(self) -> Exception:
        """The error that says why this bundle cannot turn audio into frames, and what to do instead."""
        raise NotImplementedError

    # -- shared ----------------------------------------------------------------------------------------------------
    @property
    def has_translator(self) -> bool:
        """Whether the bundle can turn audio into frames (a translator or an attached audio model)."""
        return "translator" in self.bundle.manifest["graphs"]

    @property
    def param_names(self) -> tuple[str, ...]:
        """Names of the leading parameters of `params_of`'s rows, where the rig names them (blinks use them)."""
        return ()

    param_count: int  # D, the width of `params_of`'s rows

    def load_audio(self, audio: AudioSource, sample_rate: int | None = None) -> np.ndarray:
        """Any file or array -> mono float32 at the speaker's sample rate."""
        if isinstance(audio, (str, os.PathLike)):
            return load_audio(audio, self.sample_rate)
        if sample_rate is None:
            raise AudioError("an audio array needs its sample_rate")
        return prepare_audio(audio, sample_rate, self.sample_rate)

    def run_translator(self, chunk: np.ndarray) -> dict:
        """One translator window through the bundle's translator graph (timed): mono float32 audio at the speaker's
        rate -> the graph's outputs by name. `translate_blocks` and live sessions window long audio through it."""
        if not self.has_translator:
            raise self._no_translator()
        start = time.perf_counter()
        out = self.graphs.run("translator", {"audio": chunk[None]})
        self.timings.record("translator", time.perf_counter() - start)
        return out

    @property
    def has_stream(self) -> bool:
        """Whether the bundle's translator also has a streaming graph (docs/live.md, "Streaming translators")."""
        return STREAM_GRAPH in self.bundle.manifest["graphs"]

    def run_stream(self, audio: np.ndarray, state: np.ndarray, keep: int, refresh: bool = True,
                   graphs: tuple[str, str] | None = None) -> dict:
        """One call of the streaming graph (timed): audio [B, n, F], state [B, S], `keep` frames committed;
        `refresh` False runs its steady form where the bundle has one (no frame's features made again); `graphs`:
        another stream's (refreshing, steady) graphs (`StreamSpec.graphs`), the main stream's by default."""
        start = time.perf_counter()
        refreshing, steady = graphs or STREAM_GRAPHS[0]
        graph = refreshing if refresh or steady not in self.bundle.manifest["graphs"] else steady
        out = self.graphs.run(graph, {"audio": np.ascontiguousarray(audio, np.float32),
                                      "state": np.ascontiguousarray(state, np.float32),
                                      "keep": np.array([keep], np.float32)})
        self.timings.record("translator_stream", time.perf_counter() - start)
        return out

    def stream_rows(self, out: dict) -> np.ndarray:
        """The streaming graph's outputs -> per-frame parameters [B, n, D] (the rows `params_of` gives)."""
        raise NotImplementedError

    @functools.cached_property
    def stream_spec(self) -> StreamSpec:
        """The main streaming graph's delay, frame size and rest state (one call of silence, made once)."""
        return self._read_stream_spec(STREAM_GRAPHS[0])

    @functools.cached_property
    def stream_specs(self) -> tuple[StreamSpec, ...]:
        """Every stream of the bundle's translator, the main one first: a trained speaker's also has a short one
        (docs/live.md, "A stream for a short lookahead")."""
        graphs = self.bundle.manifest["graphs"]
        return (self.stream_spec, *(self._read_stream_spec(pair) for pair in STREAM_GRAPHS[1:] if pair[0] in graphs))

    def _read_stream_spec(self, graphs: tuple[str, str]) -> StreamSpec:
        """A stream's spec from its refreshing graph's rest-state call (`graphs`: its refreshing and steady graph;
        the main stream's spec names none, as `run_stream`'s default)."""
        inputs = {value["name"]: value["shape"] for value in self.bundle.graph_info(graphs[0])["inputs"]}
        return read_stream_spec(self.run_stream, self.stream_rows, int(inputs["state"][1]), int(inputs["audio"][2]),
                                steady=graphs[1] in self.bundle.manifest["graphs"],
                                graphs=None if graphs == STREAM_GRAPHS[0] else graphs)

    def open_stream(self) -> None:
        """Open the streaming graphs and read the streams' specs now (they open on first use otherwise): a live
        server calls this at start, so that the first utterance does not stall every session on its pool thread
        for the graphs' opening (a stall re-anchors their clocks later: docs/live.md, "Load")."""
        if not self.has_stream:
            return
        for spec in self.stream_specs:
            if spec.steady:
                self.run_stream(np.zeros((1, 1, spec.frame_samples), np.float32), spec.rest_state[None], 1, False,
                                graphs=spec.graphs)

    def translate_blocks(self, audio: np.ndarray) -> Iterator[np.ndarray]:
        """Audio (speaker rate, mono float32) -> parameter blocks [n, D] in frame order, one window at a time."""
        if not self.has_translator:
            raise self._no_translator()
        return iter_translate(self.run_translator, audio, self.samples_per_frame,
                              silence_gate_dbfs=self.silence_gate_dbfs, params_of=self.params_of,
                              split=lambda params: params)

    def head_pose(self, index: int, source: HeadPoseSource = None) -> HeadPose:
        """Head pose of frame `index`: the app's (callable, [T, 6] array or fixed pose) or the pose track's."""
        if isinstance(source, HeadPose):
            return source
        if callable(source):
            return source(index)
        track = source if source is not None else self.pose_track
        if track is None:
            return HeadPose.make()
        if track is self.pose_track:  # the bundle's track, checked once (a live session's pose every frame)
            return self._pose_track().frame(index)
        return pose_track_frame(np.asarray(track, dtype=np.float32).reshape(-1, 6), index)

    def _pose_track(self) -> PoseTrack:
        """The bundle's pose track, checked once."""
        track = self.pose_track
        if self._checked_track is None or self._checked_track[0] is not track:
            self._checked_track = (track, PoseTrack(np.asarray(track, dtype=np.float32).reshape(-1, 6)))
        return self._checked_track[1]

    def head_pose_rows(self, indices: np.ndarray) -> np.ndarray:
        """`head_pose(index)` of many frames at once, as [R, 6] rows (rotation, translation)."""
        if self.pose_track is None:
            return np.zeros((len(indices), 6), np.float32)
        return self._pose_track().rows_at(np.asarray(indices, np.int64))

    def drive_rows(self, params: np.ndarray, poses: np.ndarray) -> np.ndarray | None:
        """`drive_from_params(clamp_params(row), pose)` of many frames at once (rows [R, D], poses [R, 6]), as the
        drives' fields' values in order [R, count] (what a drive message carries); None where this driver makes its
        drives one at a time, or a row fails the drive's check (drive_from_params then names it)."""
        return None

    def drives(self, audio: AudioSource, sample_rate: int | None = None,
               head_pose: HeadPoseSource = None) -> Iterator[Drive]:
        """Per-frame drives for an audio clip (translator output + head pose), translated per window."""
        index = 0
        for block in self.translate_blocks(self.load_audio(audio, sample_rate)):
            for row in block:
                yield self.drive_from_params(row, self.head_pose(index, head_pose))
                index += 1

    def frame_count(self, samples: int) -> int:
        """Video frames for `samples` audio samples: the last partial frame counts (audio is zero-padded)."""
        return math.ceil(samples / self.samples_per_frame - 1e-9)


class FlameDriver(Driver):
    """A FLAME speaker: its translator (audio -> expression [n_expr] and jaw pose [3]) or a FLAME motion."""

    rig = FLAME_RIG

    def __init__(self, bundle: Bundle, graphs: GraphBackend, config: SpeakerConfig, *, specialised: bool = False,
                 **options) -> None:
        super().__init__(bundle, graphs, **options)
        self.config, self.specialised = config, specialised
        self.fps, self.sample_rate = config.fps, config.sample_rate
        self.samples_per_frame = config.samples_per_frame
        self.param_count = config.n_expr + 3  # expression, then jaw pose

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(getattr(self.config, "expression_names", ()) or ())

    def params_of(self, out: dict, frames: int) -> np.ndarray:
        return flame_params(out, frames)

    def stream_rows(self, out: dict) -> np.ndarray:
        return np.concatenate([out["expression"], out["jaw_pose"]], axis=-1)

    def drive_from_params(self, params: np.ndarray, head_pose: HeadPose) -> FrameDrive:
        return frame_drive_of(self.config.n_expr, params, head_pose)

    def drive_rows(self, params: np.ndarray, poses: np.ndarray) -> np.ndarray | None:
        return frame_drive_rows(self.config.n_expr, self.clamp_params(params), poses)

    def drive(self, expression=None, jaw_pose=None, neck_pose=None, eye_pose=None, head_rotation=None,
              head_translation=None) -> FrameDrive:
        """The validated drive of explicit FLAME parameters and head pose (a face tracker's)."""
        return FrameDrive.make(self.config.n_expr, expression, jaw_pose, neck_pose, eye_pose,
                               HeadPose.make(head_rotation, head_translation))

    def frame_count(self, samples: int) -> int:
        return -(-samples // self.config.samples_per_frame)

    def translate(self, audio: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Audio (speaker rate, mono float32) -> expression [T, n_expr], jaw pose [T, 3] via the translator."""
        params = np.concatenate(list(self.translate_blocks(audio)))
        return params[:, :-3], params[:, -3:]

    @property
    def motion_track(self) -> FlameMotion | None:
        """The FLAME motion the bundle ships at the speaker's fps (an imported avatar's tracking), None if none."""
        if not self.bundle.has_buffer("motion_track"):
            return None
        return FlameMotion.from_table(self.bundle.buffer("motion_track"), self.fps)

    def motion(self, motion: MotionSource = None) -> FlameMotion:
        """A FLAME motion npz (GaussianAvatars' flame_param.npz keys), a FlameMotion or a [T, n_expr + 18] table at
        this speaker's fps; None: the motion the bundle ships."""
        return flame_motion(motion, self.motion_track, self.fps, self.config.n_expr, str(self.bundle.path))

    def motion_drives(self, motion: MotionSource = None, head_pose: HeadPoseSource = None) -> Iterator[FrameDrive]:
        """A FLAME motion carries its own head pose, which `head_pose` (if given) replaces."""
        track = self.motion(motion)
        for index in range(len(track)):
            yield track.drive(index, None if head_pose is None else self.head_pose(index, head_pose))

    def _no_translator(self) -> Exception:
        why = ("was specialised for a flame-driven scene" if self.specialised else
               "holds an imported avatar without an audio model")
        return BundleError(f"{self.bundle.path}: this bundle {why} and has no translator graph, so it cannot turn "
                           "audio into frames: drive it with render_params(), render() or frames(motion=...) (a "
                           f"motion file), or re-export it without --scene / {ATTACH_VOICE_HINT}")


class ArkitDriver(Driver):
    """An ARKit avatar: an attached audio model (audio -> 52 blendshape weights) or an ARKit motion."""

    rig = ARKIT_RIG

    def __init__(self, bundle: Bundle, graphs: GraphBackend, arkit: ArkitRig, **options) -> None:
        super().__init__(bundle, graphs, **options)
        self.arkit = arkit
        self.fps, self.sample_rate = arkit.fps, arkit.sample_rate
        self.samples_per_frame = arkit.sample_rate / arkit.fps
        self.param_count = len(ARKIT_BLENDSHAPES)

    @property
    def param_names(self) -> tuple[str, ...]:
        return ARKIT_BLENDSHAPES

    def params_of(self, out: dict, frames: int) -> np.ndarray:
        return blendshape_params(out, frames)

    def stream_rows(self, out: dict) -> np.ndarray:
        return np.asarray(out["blendshapes"], np.float32)

    def drive_from_params(self, params: np.ndarray, head_pose: HeadPose) -> BlendshapeDrive:
        if self.arkit.blendshapes == ARKIT_BLENDSHAPES:
            return blendshape_drive_of(params, head_pose)
        return self.drive(params, head_pose)

    def clamp_params(self, params: np.ndarray) -> np.ndarray:
        """ARKit weights are in [0, 1] (NaN stays NaN, for the drive's check to name)."""
        return np.minimum(np.maximum(params, np.float32(0.0)), np.float32(1.0))

    def drive_rows(self, params: np.ndarray, poses: np.ndarray) -> np.ndarray | None:
        if self.arkit.blendshapes != ARKIT_BLENDSHAPES:  # drive() maps them by name, a frame at a time
            return None
        return blendshape_drive_rows(self.clamp_params(params), poses)

    def drive(self, weights=None, head_pose: HeadPose | np.ndarray | None = None) -> BlendshapeDrive:
        """The validated drive of ARKit weights ({name: weight}, names left out 0, or [52] in ARKIT_BLENDSHAPES
        order) and a head pose (HeadPose or [6]: rotation about the head bone's pivot, translation; None: rest)."""
        if head_pose is not None and not isinstance(head_pose, HeadPose):
            row = np.asarray(head_pose, dtype=np.float64)
            if row.shape != (6,):
                raise DriveError(f"head_pose must be a HeadPose or [6] (rotation, translation), got shape "
                                 f"{tuple(row.shape)}")
            head_pose = HeadPose.make(row[:3], row[3:])
        if weights is not None and not isinstance(weights, dict) and self.arkit.blendshapes != ARKIT_BLENDSHAPES:
            weights = dict(zip(ARKIT_BLENDSHAPES, np.asarray(weights).reshape(-1), strict=True))
        return BlendshapeDrive.make(weights, head_pose, self.arkit.blendshapes)

    def frame_count(self, samples: int) -> int:
        return math.ceil(samples * self.fps / self.sample_rate - 1e-9)

    def translate(self, audio: np.ndarray) -> np.ndarray:
        """Audio (speaker rate, mono float32) -> the audio model's ARKit weights [T, 52]."""
        return np.concatenate(list(self.translate_blocks(audio)))

    @property
    def motion_track(self) -> MotionTrack | None:
        """The ARKit weights the bundle ships at the speaker's fps, None if none."""
        if not self.bundle.has_buffer("motion_track"):
            return None
        return MotionTrack(self.bundle.buffer("motion_track"), self.fps)

    def motion(self, motion: MotionSource = None) -> MotionTrack:
        """A motion file (LAM's JSON kinds), a MotionTrack or [T, 52] weights at this speaker's fps; None: the
        motion the bundle ships."""
        return arkit_motion(motion, self.motion_track, self.fps, str(self.bundle.path))

    def motion_drives(self, motion: MotionSource = None, head_pose: HeadPoseSource = None
                      ) -> Iterator[BlendshapeDrive]:
        """The head follows `head_pose` or the pose track."""
        track = self.motion(motion)
        for index, weights in enumerate(track.weights):
            yield self.drive(weights, self.head_pose(index, head_pose))

    def _no_translator(self) -> Exception:
        return DriveError(f"{self.bundle.path}: this ARKit speaker has no audio model attached, so it cannot turn "
                          "audio into frames: drive it with render_blendshapes(), frames(motion=...) or a motion "
                          f"file, or {ATTACH_VOICE_HINT}")


__all__ = ["ArkitDriver", "AudioSource", "Drive", "Driver", "FlameDriver", "HeadPoseSource"]
