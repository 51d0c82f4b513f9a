"""espeak-ng through its C library: speech audio and the phoneme events that time it (docs/voice.md, "Training data").

A hand-written ctypes binding, because no maintained Python package gives espeak-ng's phoneme *timings*: the PyPI
wrappers run the command line (which prints phonemes, or audio, never both with times) or phonemise text without
synthesising it. The library's synthesis callback reports each phoneme as it is spoken (its sample position in the
audio, its IPA name) when initialised with phoneme events; `espeak_TextToPhonemes` gives the same phonemes with
their stress marks, which the events lack, and the two are aligned here.

espeak-ng keeps global state (one voice, one callback), so every call here holds one lock. Its voice generator also
carries state from one utterance to the next (the pitch flutter's phase, libc's rand()), so an utterance spoken
again later in the same process can come out a few samples longer or shorter, and late in a long run a few
utterances differ from run to run; `data.speak` therefore speaks training data in short chunks, each in a fresh
process (docs/voice.md, "Training"). The library is found as
`libespeak-ng.so.1` (Debian's `libespeak-ng1`, pulled in by `apt-get install espeak-ng`) or through
`GT_ESPEAK_LIBRARY`; `available()` says whether it loads.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import difflib
import os
import threading
from dataclasses import dataclass, field

import numpy as np

from gaussiantalker.sdk.audio import resample

SAMPLE_RATE = 16000  # what `synthesize` returns (espeak-ng speaks at 22050 Hz)
PAUSE = "_"  # the phoneme name of a pause (espeak-ng reports pauses as empty names)
STRESS_MARKS = {"ˈ": 1, "ˌ": 2}  # primary, secondary
# Voiceless stops and affricates: espeak-ng reports them at the release, after their silent closure; the closure
# (digital silence, at most this long) is given back to them so the lips close where the sound stops.
CLOSURE_PHONEMES = ("p", "t", "k", "c", "q", "ʈ", "tʃ", "ts", "pf", "tɕ", "ʈʂ")
MAX_CLOSURE_S = 0.15
SILENT_LEVEL = 1e-4  # |sample| below this (re. full scale 1) is the closure's digital silence

_INIT_PHONEME_EVENTS, _INIT_PHONEME_IPA, _INIT_DONT_EXIT = 0x0001, 0x0002, 0x8000
_OUTPUT_SYNCHRONOUS = 2
_POS_CHARACTER, _CHARS_UTF8 = 1, 1
_EVENT_END_OF_LIST, _EVENT_WORD, _EVENT_PHONEME = 0, 1, 7
_RATE, _PITCH, _RANGE, _WORDGAP = 1, 3, 4, 7
_TEXT_TO_PHONEMES_IPA = 0x02 | (ord("|") << 8)  # IPA, '|' between the phonemes of a word


class _Id(ctypes.Union):
    _fields_ = [("number", ctypes.c_int), ("name", ctypes.c_char_p), ("string", ctypes.c_char * 8)]


class _Event(ctypes.Structure):
    """espeak_EVENT (speak_lib.h)."""

    _fields_ = [("type", ctypes.c_int), ("unique_identifier", ctypes.c_uint), ("text_position", ctypes.c_int),
                ("length", ctypes.c_int), ("audio_position", ctypes.c_int), ("sample", ctypes.c_int),
                ("user_data", ctypes.c_void_p), ("id", _Id)]


_Callback = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(ctypes.c_short), ctypes.c_int, ctypes.POINTER(_Event))


class EspeakError(RuntimeError):
    """espeak-ng is missing or refused a request."""


@dataclass(frozen=True)
class Phoneme:
    """One spoken phoneme: IPA name (PAUSE for a pause), [start, end) in seconds, stress (0, 1 primary,
    2 secondary) and the character of the text it was spoken from (0-based)."""

    ipa: str
    start: float
    end: float
    stress: int = 0
    text_position: int = 0


@dataclass
class Utterance:
    """Audio at SAMPLE_RATE and its phonemes, with what spoke it."""

    text: str
    voice: str
    audio: np.ndarray
    phonemes: list[Phoneme]
    settings: dict = field(default_factory=dict)

    @property
    def seconds(self) -> float:
        return self.audio.shape[0] / SAMPLE_RATE

    def to_json(self) -> dict:
        """The utterance without its audio (what tests/data keeps beside a WAV)."""
        return {"text": self.text, "voice": self.voice, "sample_rate": SAMPLE_RATE, "settings": self.settings,
                "phonemes": [{"ipa": p.ipa, "start": round(p.start, 5), "end": round(p.end, 5), "stress": p.stress,
                              "text_position": p.text_position} for p in self.phonemes]}


def phonemes_from_json(data: dict) -> list[Phoneme]:
    """The phonemes of `Utterance.to_json`."""
    return [Phoneme(str(p["ipa"]), float(p["start"]), float(p["end"]), int(p.get("stress", 0)),
                    int(p.get("text_position", 0))) for p in data["phonemes"]]


_lock = threading.Lock()
_state: dict = {}


def _library() -> ctypes.CDLL:
    """The initialised library (loaded once per process), or EspeakError."""
    if "lib" in _state:
        return _state["lib"]
    names = [os.environ.get("GT_ESPEAK_LIBRARY", ""), "libespeak-ng.so.1", ctypes.util.find_library("espeak-ng")]
    lib = None
    for name in filter(None, names):
        try:
            lib = ctypes.CDLL(name)
            break
        except OSError:
            continue
    if lib is None:
        raise EspeakError("espeak-ng's library (libespeak-ng.so.1) is not installed: apt-get install espeak-ng")
    lib.espeak_Initialize.restype = ctypes.c_int
    lib.espeak_Initialize.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_char_p, ctypes.c_int]
    lib.espeak_SetSynthCallback.argtypes = [_Callback]
    lib.espeak_SetVoiceByName.argtypes = [ctypes.c_char_p]
    lib.espeak_SetParameter.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_int]
    lib.espeak_Synth.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_uint, ctypes.c_int, ctypes.c_uint,
                                 ctypes.c_uint, ctypes.c_void_p, ctypes.c_void_p]
    lib.espeak_TextToPhonemes.restype = ctypes.c_char_p
    lib.espeak_TextToPhonemes.argtypes = [ctypes.POINTER(ctypes.c_void_p), ctypes.c_int, ctypes.c_int]
    rate = lib.espeak_Initialize(_OUTPUT_SYNCHRONOUS, 0, None,
                                 _INIT_PHONEME_EVENTS | _INIT_PHONEME_IPA | _INIT_DONT_EXIT)
    if rate <= 0:
        raise EspeakError(f"espeak-ng failed to initialise (returned {rate})")
    _state.update(lib=lib, rate=rate, chunks=[], events=[])

    def collect(wav, count, events) -> int:  # the synthesis callback: audio blocks and their events
        if count > 0:
            _state["chunks"].append(np.ctypeslib.as_array(wav, shape=(count,)).copy())
        i = 0
        while events[i].type != _EVENT_END_OF_LIST:
            event = events[i]
            if event.type == _EVENT_PHONEME:
                name = bytes(event.id.string).split(b"\0")[0].decode("utf-8", "replace")
                _state["events"].append((event.sample, name, event.text_position))
            i += 1
        return 0

    _state["callback"] = _Callback(collect)  # kept alive as long as the library may call it
    lib.espeak_SetSynthCallback(_state["callback"])
    return lib


def available() -> bool:
    """Whether espeak-ng's library loads here."""
    try:
        with _lock:
            _library()
        return True
    except EspeakError:
        return False


def _set_voice(lib: ctypes.CDLL, voice: str, rate: int, pitch: int, pitch_range: int, word_gap: int) -> None:
    if lib.espeak_SetVoiceByName(voice.encode()) != 0:
        raise EspeakError(f"espeak-ng has no voice {voice!r}")
    for parameter, value in ((_RATE, rate), (_PITCH, pitch), (_RANGE, pitch_range), (_WORDGAP, word_gap)):
        lib.espeak_SetParameter(parameter, int(value), 0)


def _stressed_phonemes(lib: ctypes.CDLL, text: str) -> list[tuple[str, int]]:
    """(IPA name, stress) of every phoneme espeak-ng makes of `text`, clause by clause (no pauses)."""
    encoded = ctypes.create_string_buffer(text.encode())
    pointer = ctypes.c_void_p(ctypes.addressof(encoded))
    found: list[tuple[str, int]] = []
    while pointer.value:
        result = lib.espeak_TextToPhonemes(ctypes.byref(pointer), _CHARS_UTF8, _TEXT_TO_PHONEMES_IPA)
        for word in (result or b"").decode("utf-8", "replace").split():
            for token in word.split("|"):
                stress = max((STRESS_MARKS.get(ch, 0) for ch in token), default=0)
                name = "".join(ch for ch in token if ch not in STRESS_MARKS)
                if name:
                    found.append((name, stress))
    return found


def _closure_start(audio: np.ndarray, sample: int, floor: int, rate: int) -> int:
    """The first sample of the digital silence ending at `sample` (a stop's closure), no earlier than `floor` nor
    MAX_CLOSURE_S before it; `sample` itself when no silence precedes it."""
    start = max(floor, sample - int(MAX_CLOSURE_S * rate))
    quiet = np.abs(audio[start:sample]) < SILENT_LEVEL
    if quiet.size == 0 or not quiet[-1]:
        return sample
    loud = np.flatnonzero(~quiet)
    return start + (int(loud[-1]) + 1 if loud.size else 0)


def _phonemes(audio: np.ndarray, events: list[tuple[int, str, int]], stresses: list[tuple[str, int]],
              rate: int) -> list[Phoneme]:
    """Phoneme events -> Phonemes: each lasts until the next event; voiceless stops take back their closure;
    stresses aligned by name (difflib) from espeak_TextToPhonemes."""
    events = [event for event in events if not event[1].startswith("(")]  # "(en)": a language switch, no sound
    names = [name or PAUSE for _, name, _ in events]
    stress = [0] * len(names)
    spoken = [i for i, name in enumerate(names) if name != PAUSE]
    matcher = difflib.SequenceMatcher(a=[names[i] for i in spoken], b=[name for name, _ in stresses], autojunk=False)
    for block in matcher.get_matching_blocks():
        for k in range(block.size):
            stress[spoken[block.a + k]] = stresses[block.b + k][1]
    starts = [min(max(sample, 0), audio.shape[0]) for sample, _, _ in events] + [audio.shape[0]]
    for i, name in enumerate(names):
        if name in CLOSURE_PHONEMES and i > 0:
            starts[i] = _closure_start(audio, starts[i], starts[i - 1] + 1, rate)
    out = []
    for i, name in enumerate(names):
        if starts[i + 1] > starts[i]:
            out.append(Phoneme(name, starts[i] / rate, starts[i + 1] / rate, stress[i], max(0, events[i][2] - 1)))
    return out


def synthesize(text: str, voice: str = "en-us", rate: int = 175, pitch: int = 50, pitch_range: int = 50,
               word_gap: int = 0) -> Utterance:
    """Speak `text` with espeak-ng: audio at SAMPLE_RATE (float32, full scale 1) and its timed phonemes.

    `voice` is an espeak-ng voice name, optionally with a variant (`en-us+f3`); `rate` in words per minute,
    `pitch` and `pitch_range` 0-100, `word_gap` in units of 10 ms."""
    with _lock:
        lib = _library()
        _set_voice(lib, voice, rate, pitch, pitch_range, word_gap)
        stresses = _stressed_phonemes(lib, text)
        _set_voice(lib, voice, rate, pitch, pitch_range, word_gap)
        _state["chunks"].clear()
        _state["events"].clear()
        data = text.encode()
        buffer = ctypes.create_string_buffer(data)
        error = lib.espeak_Synth(buffer, len(data) + 1, 0, _POS_CHARACTER, 0, _CHARS_UTF8, None, None)
        if error != 0:
            raise EspeakError(f"espeak-ng could not speak {text[:40]!r} (error {error})")
        lib.espeak_Synchronize()
        chunks, events, source_rate = list(_state["chunks"]), list(_state["events"]), _state["rate"]
    raw = (np.concatenate(chunks) if chunks else np.zeros(0, np.int16)).astype(np.float32) / 32768.0
    phonemes = _phonemes(raw, events, stresses, source_rate)
    audio = resample(raw, source_rate, SAMPLE_RATE).astype(np.float32)
    settings = {"rate": rate, "pitch": pitch, "pitch_range": pitch_range, "word_gap": word_gap}
    return Utterance(text, voice, audio, phonemes, settings)


__all__ = ["EspeakError", "PAUSE", "Phoneme", "SAMPLE_RATE", "Utterance", "available", "phonemes_from_json",
           "synthesize"]
