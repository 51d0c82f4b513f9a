"""Forced alignment of real speech: a recording and its transcript -> timed phonemes (`espeak.Phoneme`, IPA) and
how far to trust them, so the voice model can be measured on human speech (docs/voice.md, "Measurements").

pocketsphinx (the `voice` extra) aligns in two passes: the words (`set_align_text`), then the phones and HMM states
within them (`set_alignment`). Times are 10 ms frames; a phone lasts at least MIN_FRAMES (one per HMM state), so a
phone at exactly that length was squeezed. Its en-US dictionary (CMUdict, without stress) has no letter-to-sound
rules: every word of the transcript must be in it. A phone's score is its acoustic log-likelihood relative to the
best-scoring senone of each frame, in 2^SCORE_SHIFT logmath units; `Alignment` gives it in nats per frame (0: the
aligned state was the best fit in every frame).
"""

from __future__ import annotations

import difflib
import math
import re
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from gaussiantalker.sdk.audio import to_pcm16

from .arpabet import ipa_of, is_silence
from .espeak import PAUSE, Phoneme
from .segments import word_positions

SAMPLE_RATE = 16000  # the en-US acoustic model's rate
FRAMES_PER_SECOND = 100
MIN_FRAMES = 3
SCORE_SHIFT = 10  # pocketsphinx's search scores are logmath values shifted right by this (SENSCR_SHIFT)
MAX_SECONDS = 120.0  # longer clips: split them (the aligner's memory grows with frames x states)
MAX_TRANSCRIPT_CHARS = 10_000
# `poor`: the speech phones' frame-weighted mean score below POOR_MEAN_SCORE nats per frame, or more than
# POOR_SQUEEZED of them at MIN_FRAMES: the transcript does not fit the audio, or the speech is too fast or noisy for
# the model. Measured on the 13 real-speech clips (real_speech.py): with their own transcripts the mean lies in
# -1.75..-0.60 and the squeezed share in 0..0.16; with another clip's transcript, when the aligner finds a path at
# all (mostly it does not: ValueError), the mean lies in -5.4..-5.3 and the squeezed share reaches 0.29.
POOR_MEAN_SCORE = -3.0
POOR_SQUEEZED = 0.25
# Reference labels (HTS style): times in 100 ns units; at most this many bytes and lines.
LABEL_UNITS_PER_SECOND = 10_000_000
MAX_LABEL_BYTES, MAX_LABEL_LINES = 1 << 20, 20_000
# Phones told apart by stress or rhoticity only in some phone sets match each other in `reference_error`.
_MATCH_FOLD = {"ə": "ʌ", "ɚ": "ɝ", "ɨ": "ɪ"}
_WORD = re.compile(r"[^\W_]+(?:['’][^\W_]+)*")
_NON_WORDS = frozenset({"<s>", "</s>", "<sil>", "(NULL)"})


@dataclass(frozen=True)
class AlignedPhone:
    """A phone as pocketsphinx aligned it: ARPAbet name, [start, end) seconds, its frames and score (nats per
    frame, 0 best), and the index of its transcript word (None for a silence or filler)."""

    name: str
    start: float
    end: float
    frames: int
    score: float
    word: int | None


@dataclass
class Alignment:
    """A clip's phonemes (contiguous, covering [0, seconds), pauses PAUSE) and pocketsphinx's phones with the
    quality measures: the speech phones' frame-weighted mean score, the share at MIN_FRAMES, and `poor`."""

    transcript: str
    words: list[str]
    seconds: float
    phonemes: list[Phoneme]
    phones: list[AlignedPhone]
    mean_score: float
    squeezed: float
    problems: list[str] = field(default_factory=list)

    @property
    def poor(self) -> bool:
        """Whether the alignment should not be trusted (module constants POOR_MEAN_SCORE, POOR_SQUEEZED)."""
        return bool(self.problems)

    def speech_phones(self) -> list[AlignedPhone]:
        return [p for p in self.phones if p.word is not None]


@dataclass(frozen=True)
class BoundaryError:
    """Phone boundaries against a reference alignment: median and 90th percentile of |difference| in ms, over
    `boundaries` boundaries of `matched` phones matched (of `reference` in the reference)."""

    median_ms: float
    p90_ms: float
    boundaries: int
    matched: int
    reference: int


def transcript_words(transcript: str) -> list[tuple[str, int]]:
    """(word, character offset) of each word: lower-cased; punctuation separates words, except an apostrophe
    inside one ("don't"); digits stay digits (the dictionary must hold the number as written)."""
    if not isinstance(transcript, str):
        raise ValueError(f"the transcript must be a str, got {type(transcript).__name__}")
    if len(transcript) > MAX_TRANSCRIPT_CHARS:
        raise ValueError(f"the transcript has {len(transcript)} characters, more than {MAX_TRANSCRIPT_CHARS}")
    words = [(m.group(0).replace("’", "'").lower(), m.start()) for m in _WORD.finditer(transcript)]
    if not words:
        raise ValueError(f"the transcript {transcript[:80]!r} has no words")
    return words


def _pcm(audio: np.ndarray, sample_rate: int) -> bytes:
    """Mono float (-1..1) or int16 audio at SAMPLE_RATE as s16le bytes; ValueError naming what is wrong."""
    if not isinstance(sample_rate, int | float | np.integer | np.floating) or isinstance(sample_rate, bool) \
            or sample_rate != SAMPLE_RATE:
        raise ValueError(f"pocketsphinx's en-US model needs {SAMPLE_RATE} Hz audio, got {sample_rate!r} Hz: "
                         "resample it first (gaussiantalker.sdk.audio.resample)")
    samples = np.asarray(audio)
    if samples.ndim != 1:
        raise ValueError(f"audio must be mono, one dimension; got shape {samples.shape}")
    if samples.size == 0:
        raise ValueError("audio is empty (0 samples)")
    if samples.size > MAX_SECONDS * SAMPLE_RATE:
        raise ValueError(f"audio lasts {samples.size / SAMPLE_RATE:.1f} s, more than {MAX_SECONDS:g} s: split it")
    if samples.dtype == np.int16:
        return samples.astype("<i2").tobytes()
    if samples.dtype.kind != "f":
        raise ValueError(f"audio must be float (-1..1) or int16, got {samples.dtype}")
    if not np.isfinite(samples).all():
        raise ValueError("audio holds NaN or infinite samples")
    return to_pcm16(samples).astype("<i2").tobytes()


_lock = threading.RLock()  # pocketsphinx's decoder is not thread-safe
_state: dict = {}


def _decoder():
    """One pocketsphinx decoder per process for alignment (no language model; the package's en-US model)."""
    if "decoder" not in _state:
        try:
            from pocketsphinx import Decoder
        except ImportError as exc:
            raise ImportError("forced alignment needs pocketsphinx: pip install '.[voice]'") from exc
        _state["decoder"] = Decoder(lm=None, loglevel="FATAL")
        _state["nats"] = (1 << SCORE_SHIFT) * math.log(float(_state["decoder"].config["logbase"]))
    return _state["decoder"]


def missing_words(words: Sequence[str]) -> list[str]:
    """The words pocketsphinx's dictionary lacks, each once, in order."""
    with _lock:
        decoder = _decoder()
        return list(dict.fromkeys(w for w in words if decoder.lookup_word(w) is None))


def _run(decoder, pcm: bytes, text: str) -> list[tuple[str, int, int, int, list[tuple[str, int, int, int]]]]:
    """The two passes; (word, start, frames, score, [(phone, start, frames, score)]) of every aligned word."""
    decoder.set_align_text(text)
    decoder.start_utt()
    decoder.process_raw(pcm, full_utt=True)
    decoder.end_utt()
    if decoder.hyp() is None:
        raise ValueError("pocketsphinx found no alignment of the transcript (audio too short for it, or not this "
                         "transcript's speech)")
    decoder.set_alignment()
    decoder.start_utt()
    decoder.process_raw(pcm, full_utt=True)
    decoder.end_utt()
    alignment = decoder.get_alignment()
    if alignment is None:
        raise ValueError("pocketsphinx gave no phone alignment")
    out = []
    for word in alignment.words():  # iterated to the end: pocketsphinx frees its iterators there
        phones = [(p.name, p.start, p.duration, p.score) for p in word]
        out.append((word.name, word.start, word.duration, word.score, phones))
    return out


def align(audio: np.ndarray, transcript: str, sample_rate: int = SAMPLE_RATE) -> Alignment:
    """Forced alignment of `transcript` to mono `audio` at 16 kHz; ValueError naming words the dictionary lacks,
    or what else is wrong with the audio or the transcript."""
    pcm = _pcm(audio, sample_rate)
    seconds = (len(pcm) // 2) / SAMPLE_RATE
    words = transcript_words(transcript)
    with _lock:
        missing = missing_words([w for w, _ in words])
        if missing:
            raise ValueError(f"not in pocketsphinx's dictionary (it has no letter-to-sound rules; write numbers as "
                             f"words): {', '.join(repr(w) for w in missing)}")
        try:
            entries = _run(_decoder(), pcm, " ".join(w for w, _ in words))
        except (RuntimeError, ValueError) as exc:
            _state.pop("decoder", None)  # a failed pass may leave an utterance open: the next call starts afresh
            if isinstance(exc, ValueError):
                raise
            raise ValueError(f"pocketsphinx could not align the transcript: {exc}") from None
        nats = _state["nats"]
    phones: list[AlignedPhone] = []
    spoken = 0
    for name, _start, _frames, _score, parts in entries:
        index = None
        if name not in _NON_WORDS and not is_silence(name):
            if spoken >= len(words) or name.split("(")[0] != words[spoken][0]:
                raise ValueError(f"pocketsphinx aligned the word {name!r} where the transcript has "
                                 f"{words[spoken][0] if spoken < len(words) else 'no more words'!r}")
            index, spoken = spoken, spoken + 1
        for phone, start, frames, score in parts:
            frames = max(int(frames), 1)
            phones.append(AlignedPhone(phone, start / FRAMES_PER_SECOND, (start + frames) / FRAMES_PER_SECOND,
                                       frames, score * nats / frames, None if is_silence(phone) else index))
    if spoken != len(words):
        raise ValueError(f"pocketsphinx aligned {spoken} of the transcript's {len(words)} words")
    speech = [p for p in phones if p.word is not None]
    mean = sum(p.score * p.frames for p in speech) / max(sum(p.frames for p in speech), 1)
    squeezed = sum(p.frames <= MIN_FRAMES for p in speech) / max(len(speech), 1)
    problems = []
    if mean < POOR_MEAN_SCORE:
        problems.append(f"mean score {mean:.2f} nats/frame < {POOR_MEAN_SCORE}")
    if squeezed > POOR_SQUEEZED:
        problems.append(f"{squeezed:.0%} of phones at the minimum {MIN_FRAMES} frames > {POOR_SQUEEZED:.0%}")
    return Alignment(transcript, [w for w, _ in words], seconds, _phonemes(phones, words, transcript, seconds),
                     phones, mean, squeezed, problems)


def _phonemes(phones: Sequence[AlignedPhone], words: Sequence[tuple[str, int]], transcript: str,
              seconds: float) -> list[Phoneme]:
    """Contiguous phonemes over [0, seconds): gaps and silences are PAUSE (adjacent pauses merged), the last one
    stretched or cut to the clip's end; a pause's text position is the next word's (len(transcript) at the end)."""
    positions = word_positions([None if phone.word is None else words[phone.word][1] for phone in phones],
                               len(transcript))
    out: list[Phoneme] = []

    def add(ipa: str, start: float, end: float, position: int) -> None:
        end = min(end, seconds)
        if end <= start:
            return
        if ipa == PAUSE and out and out[-1].ipa == PAUSE:
            out[-1] = Phoneme(PAUSE, out[-1].start, end, 0, out[-1].text_position)
        else:
            out.append(Phoneme(ipa, start, end, 0, position))

    cursor = 0.0
    for phone, position in zip(phones, positions, strict=True):
        if phone.start > cursor:
            add(PAUSE, cursor, phone.start, position)
            cursor = phone.start
        add(ipa_of(phone.name), cursor, phone.end, position)
        cursor = max(cursor, phone.end)
    if cursor < seconds:
        add(PAUSE, cursor, seconds, len(transcript))
    return out


def read_phone_labels(data: bytes) -> list[Phoneme]:
    """Phonemes (IPA) of an HTS-style phone label file: "start end label" lines, times in 100 ns units, the label a
    phone name or a full-context label ("p1^p2-p3+p4=p5@..."); ValueError naming the line that is wrong."""
    if not isinstance(data, bytes | bytearray):
        raise ValueError(f"a label file is bytes, got {type(data).__name__}")
    if len(data) > MAX_LABEL_BYTES:
        raise ValueError(f"label file of {len(data)} bytes, more than {MAX_LABEL_BYTES}")
    try:
        text = bytes(data).decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"label file is not UTF-8 text: {exc}") from None
    lines = [line for line in text.splitlines() if line.strip()]
    if not lines:
        raise ValueError("label file holds no labels")
    if len(lines) > MAX_LABEL_LINES:
        raise ValueError(f"label file of {len(lines)} lines, more than {MAX_LABEL_LINES}")
    out: list[Phoneme] = []
    previous_end = 0
    for number, line in enumerate(lines, 1):
        fields = line.split()
        if len(fields) != 3 or not (fields[0].isascii() and fields[0].isdigit() and fields[1].isascii()
                                    and fields[1].isdigit()) or max(len(fields[0]), len(fields[1])) > 15:
            raise ValueError(f"label line {number}: expected 'start end label' with whole times in 100 ns "
                             f"units, got {line[:80]!r}")
        start, end = int(fields[0]), int(fields[1])
        if end <= start or start < previous_end:
            raise ValueError(f"label line {number}: times {start}..{end} do not follow {previous_end}")
        label = fields[2]
        current = label.split("-", 1)[1].split("+", 1)[0] if "-" in label and "+" in label else label
        try:
            ipa = ipa_of(current)
        except ValueError:
            raise ValueError(f"label line {number}: {current[:40]!r} is not an ARPAbet phone") from None
        out.append(Phoneme(ipa, start / LABEL_UNITS_PER_SECOND, end / LABEL_UNITS_PER_SECOND))
        previous_end = end
    return out


def _match_key(ipa: str) -> str:
    return _MATCH_FOLD.get(ipa, ipa)


def reference_error(alignment: Alignment | Sequence[Phoneme], reference_phones: Sequence[Phoneme]) -> BoundaryError:
    """How far the alignment's phone boundaries lie from a reference alignment's: phones matched by name
    (difflib, pauses included, schwa matching /ʌ/), one boundary per matched phone, its start (the clip's first
    start excluded: both are 0)."""
    ours = alignment.phonemes if isinstance(alignment, Alignment) else list(alignment)
    theirs = list(reference_phones)
    matcher = difflib.SequenceMatcher(None, [_match_key(p.ipa) for p in ours], [_match_key(p.ipa) for p in theirs],
                                      autojunk=False)
    differences, matched = [], 0
    for block in matcher.get_matching_blocks():
        for k in range(block.size):
            a, b = ours[block.a + k], theirs[block.b + k]
            matched += 1
            if block.a + k == 0 and block.b + k == 0:
                continue
            differences.append(abs(a.start - b.start) * 1000.0)
    if not differences:
        raise ValueError("no phone boundaries in common with the reference")
    values = np.asarray(differences)
    return BoundaryError(float(np.median(values)), float(np.percentile(values, 90)), len(differences), matched,
                         len(theirs))


__all__ = ["AlignedPhone", "Alignment", "BoundaryError", "FRAMES_PER_SECOND", "MIN_FRAMES", "POOR_MEAN_SCORE",
           "POOR_SQUEEZED", "SAMPLE_RATE", "align", "missing_words", "read_phone_labels", "reference_error",
           "transcript_words"]
