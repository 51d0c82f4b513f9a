"""What a live face does between turns: blinks on their own rhythm, a slow sway and breath when the bundle has no
pose track, and a smooth ease from the last spoken frame to the neutral face (docs/live.md, "Idle")."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gaussiantalker.sdk.drive import HeadPose
from gaussiantalker.sdk.errors import SettingsError

# Names of the eyelid-closing coefficients looked up in a speaker's parameter names (ARKit's, or a FLAME
# speaker's named expression basis such as the demo speaker's).
BLINK_NAMES = ("eyeBlinkLeft", "eyeBlinkRight", "blink_left", "blink_right")


@dataclass(frozen=True)
class IdleMotion:
    """Idle behaviour of a live session. `blink`: the parameter offset of closed eyes ([D], in the speaker's
    drive order), None to look it up by name (BLINK_NAMES), zeros for no blinks. Blinks last `blink_ms` and start
    every `blink_interval_s` (uniform in the range, seeded by `seed`) while idle. Without a pose track the head
    sways by `sway_deg` and breathes by `breath_mm` (0 turns either off). `ease_ms`: from the last spoken frame
    (or a barge-in) to the neutral face."""

    blink: np.ndarray | None = None
    blink_ms: float = 160.0
    blink_interval_s: tuple[float, float] = (2.5, 5.5)
    sway_deg: float = 1.0
    breath_mm: float = 1.0
    ease_ms: float = 120.0
    seed: int = 0

    def __post_init__(self) -> None:
        low, high = (float(v) for v in self.blink_interval_s)
        checks = {"blink_ms": self.blink_ms, "sway_deg": self.sway_deg, "breath_mm": self.breath_mm,
                  "ease_ms": self.ease_ms, "blink_interval_s": low}
        for name, value in checks.items():
            if not (math.isfinite(float(value)) and float(value) >= 0):
                raise SettingsError(f"IdleMotion.{name} must be a finite number >= 0, got {value!r}")
        if not (math.isfinite(high) and high >= low > 0):
            raise SettingsError(f"IdleMotion.blink_interval_s must be (low, high) with 0 < low <= high, "
                                f"got {self.blink_interval_s!r}")


def blink_vector(names: tuple[str, ...] | None, size: int, blink: np.ndarray | None) -> np.ndarray:
    """The closed-eyes offset [size]: the app's, else 1 on every parameter named in BLINK_NAMES, else zeros."""
    if blink is not None:
        vector = np.asarray(blink, np.float32).reshape(-1)
        if vector.shape != (size,) or not np.all(np.isfinite(vector)):
            raise SettingsError(f"IdleMotion.blink must be {size} finite values (the speaker's drive order), "
                                f"got shape {vector.shape}")
        return vector
    vector = np.zeros(size, np.float32)
    for index, name in enumerate(names or ()):
        if index < size and name in BLINK_NAMES:
            vector[index] = 1.0
    return vector


def smoothstep(x: float) -> float:
    """0 at x <= 0, 1 at x >= 1, zero slope at both ends."""
    x = min(max(x, 0.0), 1.0)
    return x * x * (3.0 - 2.0 * x)


class IdleTrack:
    """Per-frame idle motion of one session at `fps`: blink weight, ease weight, fallback head pose."""

    def __init__(self, motion: IdleMotion, fps: float) -> None:
        self.motion, self.fps = motion, fps
        self._rng = np.random.default_rng(motion.seed)
        self._blink_frames = max(1, round(motion.blink_ms * fps / 1000.0)) if motion.blink_ms > 0 else 0
        self.ease_frames = round(motion.ease_ms * fps / 1000.0)
        self._blink_start: int | None = None
        self._next_blink = self._interval()

    def _interval(self) -> int:
        low, high = self.motion.blink_interval_s
        return max(1, round(float(self._rng.uniform(low, high)) * self.fps))

    def blink_weight(self, index: int, idle: bool) -> float:
        """Eyelid closure in [0, 1] at frame `index`. A blink starts only on an idle frame, then runs to its end
        even if speech resumes (cutting it would snap the eyelids open)."""
        if not self._blink_frames:
            return 0.0
        if self._blink_start is not None and index >= self._blink_start + self._blink_frames:
            self._blink_start = None
        if self._blink_start is None:
            if not idle or index < self._next_blink:
                return 0.0
            self._blink_start, self._next_blink = index, index + self._blink_frames + self._interval()
        phase = (index - self._blink_start + 0.5) / self._blink_frames
        return float(math.sin(math.pi * phase))

    def ease_weight(self, frames_since_speech: int) -> float:
        """Weight of the last spoken frame's parameters `frames_since_speech` (1, 2, ...) frames after it."""
        if self.ease_frames <= 0:
            return 0.0
        return 1.0 - smoothstep(frames_since_speech / self.ease_frames)

    def sway(self, index: int) -> HeadPose:
        """A slow head sway (incommensurate periods near 7-11 s) and breath (4 s): the fallback head pose."""
        t = index / self.fps
        amplitude = math.radians(self.motion.sway_deg)
        rotation = amplitude * np.array([0.6 * math.sin(2 * math.pi * t / 9.1 + 1.0),
                                         math.sin(2 * math.pi * t / 11.3), 0.4 * math.sin(2 * math.pi * t / 7.3 + 2.0)])
        breath = self.motion.breath_mm * 1e-3 * math.sin(2 * math.pi * t / 4.0)
        return HeadPose.make(rotation, np.array([0.0, breath, 0.0]))
