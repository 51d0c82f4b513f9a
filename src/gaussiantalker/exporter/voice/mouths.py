"""What each audio driver does with a mouth, in one currency, so one set of gates measures them all
(docs/voice.md, "Measurements"): the built-in ARKit and FLAME voice models and a bundle's own translator.

A driver under test turns 16 kHz audio into a `MouthTrack` at 25 fps:
* `aperture`: how far the lips are apart, in jawOpen units (1 = the opening of ARKit's jawOpen 1, which the
  FLAME driver maps to a JAW_RADIANS jaw rotation): the ARKit model's jawOpen - mouthClose; the FLAME model's jaw
  rotation / JAW_RADIANS (its committed graph closes the jaw for mouthClose); a bundle speaker's lip gap measured
  on its deformed Gaussians (`LipGap`), divided by the gap a JAW_RADIANS jaw rotation alone opens on that head;
* `jaw`: the jaw's opening in the same units (what follows loudness);
* `weights`: the 52 ARKit weights, where the driver has them (the channels' agreement with the phoneme targets).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort

from gaussiantalker.runtime.translate import resample_rows
from gaussiantalker.sdk.audio import resample
from gaussiantalker.sdk.rig import ARKIT_BLENDSHAPES

from .flame_fit import JAW_RADIANS
from .targets import FPS

SAMPLE_RATE = 16000
JAW, CLOSE = ARKIT_BLENDSHAPES.index("jawOpen"), ARKIT_BLENDSHAPES.index("mouthClose")
JAW_JOINT_POSE = slice(6, 9)  # flame_pose = global, neck, jaw, left eye, right eye (3 each)
MIDLINE_SHARE = 0.3  # lip Gaussians within this share of the mouth's half-width of its centre line ...
MIDLINE_LEAST = 12  # ... or the nearest this many to it, in a head with few Gaussians
GAP_PERCENTILE = 20  # the upper lip's 20th-percentile height over the lower lip's 80th: robust to stray Gaussians


@dataclass
class MouthTrack:
    """A driver's mouth over a clip, 25 fps: aperture [T] and jaw [T] in jawOpen units, ARKit weights [T, 52] or
    None."""

    aperture: np.ndarray
    jaw: np.ndarray
    weights: np.ndarray | None = None


def _session(model: bytes | str | os.PathLike) -> ort.InferenceSession:
    """One-thread onnxruntime session (the measurements' cost figures are per core)."""
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    source = model if isinstance(model, bytes) else str(model)
    return ort.InferenceSession(source, options, providers=["CPUExecutionProvider"])


class ArkitVoice:
    """The built-in ARKit voice model (audio [1, S] -> blendshapes [1, T, 52]) on a whole clip."""

    def __init__(self, model: bytes | str | os.PathLike, name: str = "ARKit voice") -> None:
        self.name, self.session = name, _session(model)

    def run(self, audio: np.ndarray) -> np.ndarray:
        """The driver's own work: weights [T, 52]."""
        return self.session.run(["blendshapes"], {"audio": np.ascontiguousarray(audio, np.float32)[None]})[0][0]

    def mouth(self, audio: np.ndarray) -> MouthTrack:
        weights = self.run(audio)
        return MouthTrack(weights[:, JAW] - weights[:, CLOSE], weights[:, JAW].copy(), weights)


class FlameVoice:
    """The built-in FLAME voice model (audio -> expression, jaw_pose) as committed: its jaw carries the mouth."""

    def __init__(self, model: bytes | str | os.PathLike, name: str = "FLAME voice") -> None:
        self.name, self.session = name, _session(model)

    def run(self, audio: np.ndarray) -> np.ndarray:
        """The driver's own work: jaw poses [T, 3] (the expression, all zero without a FLAME, is not read)."""
        return self.session.run(["jaw_pose"], {"audio": np.ascontiguousarray(audio, np.float32)[None]})[0][0]

    def mouth(self, audio: np.ndarray) -> MouthTrack:
        opening = self.run(audio)[:, 0] / JAW_RADIANS
        return MouthTrack(opening, opening.copy())


class LipGap:
    """A FLAME bundle's lip opening measured on its Gaussians: the vertical gap between the upper and the lower
    lip's Gaussians near the mouth's centre line, rest pose 0, in jawOpen units (module docstring)."""

    def __init__(self, head) -> None:
        from gaussiantalker.runtime.semantic import Regions

        regions = Regions(head.bundle)
        if "lips" not in regions.names:
            raise ValueError(f"{head.bundle.path}: no 'lips' region, so its lip gap cannot be measured")
        self.head, self.n_expr = head, head.driver.config.n_expr
        rest = self._means(np.zeros((1, 3), np.float32))[0]
        opened = self._means(np.array([[JAW_RADIANS, 0.0, 0.0]], np.float32))[0]
        lips = np.flatnonzero(regions.ids == regions.names.index("lips"))
        x = rest[lips, 0]
        centre, half_width = 0.5 * (x.min() + x.max()), 0.5 * (x.max() - x.min())
        distance = np.abs(x - centre)
        mid = lips[(distance < MIDLINE_SHARE * half_width) | (distance <= np.sort(distance)[
            min(MIDLINE_LEAST, distance.size) - 1])]
        drop = opened[mid, 1] - rest[mid, 1]  # the lower lip rides the jaw down
        self.lower, self.upper = mid[drop < 0.5 * drop.min()], mid[drop >= 0.5 * drop.min()]
        if self.lower.size < 3 or self.upper.size < 3:
            raise ValueError(f"{head.bundle.path}: the lips' Gaussians do not part into an upper and a lower lip")
        self.rest_gap = float(self._gaps(rest[None])[0])
        self.unit = float(self._gaps(opened[None])[0]) - self.rest_gap

    def _means(self, jaw_pose: np.ndarray, expression: np.ndarray | None = None) -> np.ndarray:
        frames = jaw_pose.shape[0]
        pose = np.zeros((frames, 15), np.float32)
        pose[:, JAW_JOINT_POSE] = jaw_pose
        inputs = {"expression": (np.zeros((frames, self.n_expr), np.float32) if expression is None
                                 else expression.astype(np.float32)),
                  "flame_pose": pose, "head_translation": np.zeros((frames, 3), np.float32),
                  "camera_center": np.repeat(self.head.camera.center.astype(np.float32)[None], frames, 0)}
        return self.head.frame_renderer.graphs.run("deform", inputs)["means"]

    def _gaps(self, means: np.ndarray) -> np.ndarray:
        upper = np.percentile(means[:, self.upper, 1], GAP_PERCENTILE, axis=1)
        lower = np.percentile(means[:, self.lower, 1], 100 - GAP_PERCENTILE, axis=1)
        return upper - lower

    def apertures(self, expression: np.ndarray, jaw_pose: np.ndarray, batch: int = 64) -> np.ndarray:
        """Aperture per frame [T] of explicit FLAME parameters (the head still)."""
        out = [self._gaps(self._means(jaw_pose[k:k + batch], expression[k:k + batch]))
               for k in range(0, len(jaw_pose), batch)]
        return (np.concatenate(out) - self.rest_gap) / self.unit


class BundleSpeaker:
    """A FLAME bundle's own translator (e.g. the demo speaker's), through the runtime's offline path, its mouth
    measured on its Gaussians (`LipGap`); its frames resampled to 25 fps when it runs at another rate."""

    def __init__(self, bundle: str | os.PathLike, name: str | None = None) -> None:
        from gaussiantalker.runtime.head import TalkingHead

        self.head = TalkingHead(bundle, renderer="cpu", threads=1, composite=False)
        if self.head.driver.rig != "flame":
            raise ValueError(f"{bundle}: gt-bench voice measures FLAME bundles' translators (this one is "
                             f"{self.head.driver.rig})")
        self.name = name or f"{Path(bundle).stem} translator"
        self.lips = LipGap(self.head)

    def run(self, audio: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The driver's own work: the runtime's offline translation, (expression [T, n], jaw pose [T, 3])."""
        driver = self.head.driver
        return driver.translate(resample(np.asarray(audio, np.float32), SAMPLE_RATE, driver.sample_rate
                                         ).astype(np.float32))

    def mouth(self, audio: np.ndarray) -> MouthTrack:
        driver = self.head.driver
        expression, jaw_pose = self.run(audio)
        aperture = self.lips.apertures(expression, jaw_pose)
        jaw = jaw_pose[:, 0] / JAW_RADIANS
        if driver.fps != FPS:
            frames = int(round(len(jaw) * FPS / driver.fps))
            aperture = resample_rows(aperture[:, None], frames)[:, 0]
            jaw = resample_rows(jaw[:, None], frames)[:, 0]
        return MouthTrack(aperture, jaw)


__all__ = ["ArkitVoice", "BundleSpeaker", "FlameVoice", "LipGap", "MouthTrack"]
