"""Speech no training voice spoke, for the streaming translators' tests: the held-out espeak-ng clip, and the real
recordings .ci/install fetches (tests that need them skip where they are missing, and fail in CI)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from ci_tools import need

HELDOUT = Path(__file__).resolve().parent / "data" / "voice_heldout"


def unseen_speech() -> list[np.ndarray]:
    """The held-out espeak-ng clip, then up to three real recordings (16 kHz mono float32)."""
    from gaussiantalker.exporter.voice import real_speech
    from gaussiantalker.exporter.voice.data import load_utterance

    clips = [load_utterance(HELDOUT).audio]
    try:
        clips += [clip.audio for clip in real_speech.load()[:3]]
    except real_speech.RealSpeechMissing as exc:
        need(str(exc), ".ci/install (its real-speech fetch step)")
    return clips
