"""What festival and flite share (docs/voice.md, "Voices"): a synthesis request, and their timed segments (ARPAbet,
or a festival phone set of phonesets.py) -> `Phoneme`s, with each segment's word found in the text.

Both engines give a segment list (phone name, end time, its syllable's stress, the token of the text its word came
from); a segment starts where the one before it ends, so the phonemes are contiguous by construction, and the last
one is stretched or cut to the audio's end so that they cover it exactly.
"""

from __future__ import annotations

import math
import unicodedata
from collections.abc import Sequence
from dataclasses import dataclass

from .arpabet import VOWELS, ipa_of, is_silence, split_stress
from .espeak import Phoneme
from .phonesets import PhoneSet

TEMPO_RANGE, PITCH_RANGE_HZ = (0.25, 4.0), (40.0, 400.0)  # what a request may ask


@dataclass(frozen=True)
class Request:
    """One utterance to speak: `tempo` stretches durations (1.3: 1.3x longer), `pitch` is the target mean F0 in Hz
    (None: the voice's own; ignored by voices that cannot change it)."""

    text: str
    voice: str
    tempo: float = 1.0
    pitch: float | None = None


@dataclass(frozen=True)
class Row:
    """One engine segment: phone name, end (s), its syllable's stress feature, its token's index (None: a pause)."""

    name: str
    end: float
    stress: int
    token: int | None


def request_problem(request: Request) -> str | None:
    """What is wrong with a request's text, tempo or pitch (None: nothing); the engine's error carries it."""
    if not any(ch.isascii() and ch.isalnum() for ch in request.text):  # festival crashes on some such text
        return f"empty text to speak: no English letter or digit in {request.text[:60]!r} (voice {request.voice!r})"
    if not (math.isfinite(request.tempo) and TEMPO_RANGE[0] <= request.tempo <= TEMPO_RANGE[1]):
        return f"tempo {request.tempo!r} is outside {TEMPO_RANGE}"
    if request.pitch is not None and not (math.isfinite(request.pitch)
                                          and PITCH_RANGE_HZ[0] <= request.pitch <= PITCH_RANGE_HZ[1]):
        return f"pitch {request.pitch!r} Hz is outside {PITCH_RANGE_HZ}"
    return None


def clean_text(text: str) -> str:
    """`text` with control and format characters (newlines, NUL, lone surrogates) made spaces: what an engine
    reads; character offsets are unchanged."""
    return "".join(" " if unicodedata.category(ch) in ("Cc", "Cf", "Cs", "Zl", "Zp") else ch for ch in text)


def token_offsets(text: str, tokens: Sequence[str]) -> list[int]:
    """Character offset of each token in `text`, found in order (case-insensitive) from the end of the last one
    found; a token not found (an engine's rewriting) takes the offset where the search stands."""
    lowered, offsets, cursor = text.lower(), [], 0
    for token in tokens:
        at = lowered.find(token.lower(), cursor) if token else -1
        if at < 0:
            offsets.append(min(cursor, len(text)))
            continue
        offsets.append(at)
        cursor = at + len(token)
    return offsets


def word_positions(word_offsets: Sequence[int | None], end: int) -> list[int]:
    """Text position of each phone from its word's character offset (None: a pause, which takes the next word's
    offset, or `end` after the last word)."""
    positions = [end] * len(word_offsets)
    following = end
    for i in range(len(word_offsets) - 1, -1, -1):
        if word_offsets[i] is not None:
            following = word_offsets[i]
        positions[i] = following
    return positions


def phone_ipa(name: str, stress: int) -> str:
    """IPA of an engine phone, its syllable's stress read as the vowel's stress digit (unstressed "ah" is a schwa)."""
    phone, digit = split_stress(name)
    if phone in VOWELS and digit is None:
        phone = f"{phone}{1 if stress == 1 else 0}"
    return ipa_of(phone)


def phonemes_of(rows: Sequence[Row], tokens: Sequence[str], text: str, seconds: float,
                phones: PhoneSet | None = None) -> list[Phoneme]:
    """Rows -> contiguous Phonemes over [0, seconds): IPA names; stress 1 on a vowel whose syllable's stress is 1,
    else 0 (both engines' lexicons fold secondary stress into 1: "understand" is 1 0 1; a phone set may mark a
    stressed vowel in its name instead, or stress each word's first vowel); text_position the offset
    of the segment's word in `text` (a pause: the next word's, or len(text) after the last). The phones are ARPAbet,
    or of `phones` where given. ValueError names a phone that is in neither."""
    silence = is_silence if phones is None else phones.is_silence
    offsets = token_offsets(text, tokens)
    position = word_positions([offsets[row.token] if row.token is not None and 0 <= row.token < len(offsets)
                               and not silence(row.name) else None for row in rows], len(text))
    out: list[Phoneme] = []
    start = 0.0
    stressed_words: set[int] = set()  # words whose first vowel was seen (a phone set with initial stress)
    for i, row in enumerate(rows):
        end = seconds if i == len(rows) - 1 else min(max(row.end, start), seconds)
        if phones is None:
            ipa = phone_ipa(row.name, row.stress)
            stress = 1 if row.stress == 1 and split_stress(row.name)[0] in VOWELS else 0
        else:  # a set whose vowels carry their stress in the name, or one whose syllables do
            ipa = phones.ipa_of(row.name)
            vowel = phones.is_vowel(row.name)
            initial = phones.initial_stress and vowel and row.token is not None and row.token not in stressed_words
            if initial:
                stressed_words.add(row.token)
            stress = 1 if vowel and (row.stress == 1 or phones.stressed(row.name) or initial) else 0
        if end > start:
            out.append(Phoneme(ipa, start, end, stress, position[i]))
        start = end
    return out


__all__ = ["PITCH_RANGE_HZ", "Request", "Row", "TEMPO_RANGE", "clean_text", "phone_ipa", "phonemes_of",
           "request_problem", "token_offsets", "word_positions"]
