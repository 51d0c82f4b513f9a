"""English speech with its phone timings from flite's C library (docs/voice.md, "Voices").

A hand-written ctypes binding, because no maintained Python package gives flite's phone timings with their stress:
the wrappers run the command line, whose -psdur listing has phones and durations but no stress and no words. The
library synthesises an utterance whose Segment relation carries each phone's end time, its syllable's stress and
(through SylStructure and Token) the word of the text it came from; the wave is in the same utterance.

flite keeps global state (registered voices and their features, libc's rand() that its clustergen voices draw
their unvoiced excitation from), so every call here holds one lock, seeds rand() (RAND_SEED) before it speaks and
sets the voice features it changes back afterwards: an utterance depends on its own arguments only, whatever was
spoken before and in whichever process. Seeding rand() also resets it for anything else in the process that uses
libc's rand() (espeak-ng does). A flite error inside the library ends the process (flite's cst_error), as it would
in any program using it.

Voices (Debian's libflite1): `slt`, `rms`, `awb` (clustergen statistical voices, 16 kHz), `kal16` (diphone,
16 kHz) and `kal` (diphone, 8 kHz: resampled, no energy above 4 kHz). Tempo is the voice feature
`duration_stretch` (times the voice's own: kal's is 1.1), pitch its `int_f0_target_mean` (Hz); `rms` draws its
F0 from an accent model (spamf0) that ignores the target, so its pitch cannot be set and `pitch` is ignored.

Deterministic (tests/test_voice_synths.py): as above. Timing, measured on a few sentences: segments are ARPAbet
phones, so a voiceless stop's segment holds its closure, burst and aspiration; it starts where the vowel before it
begins to fade, the energy falls steepest a median 25 ms (slt), 16 ms (rms), 6 ms (awb), 21 ms (kal16, kal) after
its start and is 10-30 dB below the vowel's 10-20 ms into it (a noise floor, not digital silence); the burst comes
at ~55-75 % of it. Lips closing at the segment's start thus close about half a frame early. Vowel onsets after
nasals and fricatives lie within a median 6 ms of the segment boundary. A diphone voice's last segment may end after
its audio, and is cut to it.
"""

from __future__ import annotations

import ctypes
import threading
from collections.abc import Sequence

import numpy as np

from gaussiantalker.sdk.audio import resample

from .espeak import PAUSE, SAMPLE_RATE, Utterance
from .segments import Request, Row, clean_text, phonemes_of, request_problem

VOICES: dict[str, str] = {  # short name -> the voice's library (register_<name> makes the voice)
    "slt": "cmu_us_slt",
    "rms": "cmu_us_rms",
    "awb": "cmu_us_awb",
    "kal16": "cmu_us_kal16",
    "kal": "cmu_us_kal",
}
FIXED_PITCH = frozenset({"rms"})  # its F0 comes from an accent model that ignores int_f0_target_mean
RAND_SEED = 1  # libc's rand() as a fresh process starts it
# Feature names flite keeps by pointer (it never copies them): buffers that live as long as the process.
_DURATION_STRETCH = ctypes.create_string_buffer(b"duration_stretch")
_F0_MEAN = ctypes.create_string_buffer(b"int_f0_target_mean")


class FliteError(RuntimeError):
    """flite's library or a voice is missing, or it could not speak a request."""


class _Wave(ctypes.Structure):
    """cst_wave (cst_wave.h)."""

    _fields_ = [("type", ctypes.c_char_p), ("sample_rate", ctypes.c_int), ("num_samples", ctypes.c_int),
                ("num_channels", ctypes.c_int), ("samples", ctypes.POINTER(ctypes.c_short))]


class _Voice(ctypes.Structure):
    """cst_voice (cst_voice.h): its name and features come first."""

    _fields_ = [("name", ctypes.c_char_p), ("features", ctypes.c_void_p), ("ffunctions", ctypes.c_void_p)]


_lock = threading.Lock()
_state: dict = {"voices": {}}
_SIGNATURES = {  # name: (restype, argtypes), as flite's headers declare them
    "flite_init": (ctypes.c_int, []),
    "flite_synth_text": (ctypes.c_void_p, [ctypes.c_char_p, ctypes.c_void_p]),
    "utt_wave": (ctypes.POINTER(_Wave), [ctypes.c_void_p]),
    "utt_relation": (ctypes.c_void_p, [ctypes.c_void_p, ctypes.c_char_p]),
    "relation_head": (ctypes.c_void_p, [ctypes.c_void_p]),
    "item_next": (ctypes.c_void_p, [ctypes.c_void_p]),
    "path_to_item": (ctypes.c_void_p, [ctypes.c_void_p, ctypes.c_char_p]),
    "ffeature_string": (ctypes.c_char_p, [ctypes.c_void_p, ctypes.c_char_p]),
    "ffeature_float": (ctypes.c_float, [ctypes.c_void_p, ctypes.c_char_p]),
    "delete_utterance": (None, [ctypes.c_void_p]),
    "feat_present": (ctypes.c_int, [ctypes.c_void_p, ctypes.c_char_p]),
    "feat_float": (ctypes.c_float, [ctypes.c_void_p, ctypes.c_char_p]),
    "feat_set_float": (None, [ctypes.c_void_p, ctypes.c_char_p, ctypes.c_float]),
    "feat_remove": (ctypes.c_int, [ctypes.c_void_p, ctypes.c_char_p]),
}


def _library() -> ctypes.CDLL:
    """libflite, initialised once per process (call with the lock held), or FliteError."""
    if "lib" not in _state:
        try:
            lib = ctypes.CDLL("libflite.so.1", mode=ctypes.RTLD_GLOBAL)
        except OSError as exc:
            raise FliteError("flite's library (libflite.so.1) is not installed (Debian: apt-get install "
                             "libflite1)") from exc
        for name, (restype, argtypes) in _SIGNATURES.items():
            function = getattr(lib, name)
            function.restype, function.argtypes = restype, argtypes
        lib.flite_init()
        libc = ctypes.CDLL(None)
        libc.srand.argtypes, libc.srand.restype = [ctypes.c_uint], None
        _state.update(lib=lib, libc=libc)
    return _state["lib"]


def _voice(voice: str) -> ctypes._Pointer[_Voice]:
    """The registered voice (once per process; call with the lock held), or FliteError."""
    if voice not in VOICES:
        raise FliteError(f"flite has no voice {voice!r} here (known: {', '.join(VOICES)})")
    _library()
    if voice not in _state["voices"]:
        name = VOICES[voice]
        try:
            library = ctypes.CDLL(f"libflite_{name}.so.1")
        except OSError as exc:
            raise FliteError(f"flite's voice {voice!r} (libflite_{name}.so.1) is not installed (Debian: apt-get "
                             "install libflite1)") from exc
        register = getattr(library, f"register_{name}")
        register.restype, register.argtypes = ctypes.POINTER(_Voice), [ctypes.c_char_p]
        pointer = register(None)
        if not pointer:
            raise FliteError(f"flite could not register its voice {voice!r}")
        _state["voices"][voice] = (library, pointer)
    return _state["voices"][voice][1]


def available(voice: str | None = None) -> bool:
    """Whether flite's library loads here (and `voice`, one of VOICES, registers)."""
    try:
        with _lock:
            _library()
            if voice is not None:
                _voice(voice)
        return True
    except FliteError:
        return False


def _rows(lib: ctypes.CDLL, utterance: int) -> tuple[list[str], list[Row]]:
    """The utterance's top-level tokens (names) and its segments (name, end, stress, token index)."""
    tokens: list[str] = []
    index: dict[int, int] = {}
    item = lib.relation_head(lib.utt_relation(utterance, b"Token"))
    while item:
        index[item] = len(tokens)
        tokens.append((lib.ffeature_string(item, b"name") or b"").decode("utf-8", "replace"))
        item = lib.item_next(item)
    rows: list[Row] = []
    item = lib.relation_head(lib.utt_relation(utterance, b"Segment"))
    while item:
        name = (lib.ffeature_string(item, b"name") or b"").decode("utf-8", "replace")
        stress = int(float(lib.ffeature_string(item, b"R:SylStructure.parent.stress") or b"0"))
        token = lib.path_to_item(item, b"R:SylStructure.parent.parent.R:Token.parent")
        rows.append(Row(name, float(lib.ffeature_float(item, b"end")), stress, index.get(token) if token else None))
        item = lib.item_next(item)
    return tokens, rows


def _speak(request: Request) -> tuple[np.ndarray, int, list[str], list[Row]]:
    """(int16 samples, sample rate, tokens, rows) of one request, with the lock held."""
    lib = _library()
    voice = _voice(request.voice)
    features = voice.contents.features
    names = [_DURATION_STRETCH] + ([_F0_MEAN] if _applied_pitch(request) is not None else [])
    saved = [(name, float(lib.feat_float(features, name)) if lib.feat_present(features, name) else None)
             for name in names]  # feat_float of an absent feature is a fatal error
    try:
        stretch = saved[0][1] if saved[0][1] is not None else 1.0  # kal's own is 1.1: tempo 1 keeps it
        lib.feat_set_float(features, _DURATION_STRETCH, stretch * request.tempo)
        if len(names) > 1:
            lib.feat_set_float(features, _F0_MEAN, float(request.pitch))
        _state["libc"].srand(RAND_SEED)
        utterance = lib.flite_synth_text(clean_text(request.text).encode("utf-8"), voice)
        if not utterance:
            raise FliteError(f"flite could not speak {request.text[:60]!r} with {request.voice!r}")
        try:
            wave = lib.utt_wave(utterance)
            if not wave or wave.contents.num_samples <= 0 or wave.contents.num_channels != 1:
                raise FliteError(f"flite spoke no audio for {request.text[:60]!r} with {request.voice!r}")
            samples = np.ctypeslib.as_array(wave.contents.samples, shape=(wave.contents.num_samples,)).copy()
            tokens, rows = _rows(lib, utterance)
            return samples, int(wave.contents.sample_rate), tokens, rows
        finally:
            lib.delete_utterance(utterance)
    finally:
        for name, value in saved:
            if value is not None:
                lib.feat_set_float(features, name, value)
            else:
                lib.feat_remove(features, name)


def _applied_pitch(request: Request) -> float | None:
    return None if request.voice in FIXED_PITCH else request.pitch


def synthesize_many(requests: Sequence[Request]) -> list[Utterance]:
    """Speak every request, in order (each depends on its own request only: module docstring)."""
    for request in requests:
        problem = request_problem(request)
        if problem:
            raise FliteError(f"flite: {problem}")
        if request.voice not in VOICES:
            raise FliteError(f"flite has no voice {request.voice!r} here (known: {', '.join(VOICES)})")
    out = []
    for request in requests:
        with _lock:
            samples, rate, tokens, rows = _speak(request)
        audio = resample(samples.astype(np.float32) / 32768.0, rate, SAMPLE_RATE).astype(np.float32)
        try:
            phonemes = phonemes_of(rows, tokens, request.text, audio.shape[0] / SAMPLE_RATE)
        except ValueError as exc:
            raise FliteError(f"flite spoke {request.text[:60]!r} with a phone it should not: {exc}") from exc
        if not any(p.ipa != PAUSE for p in phonemes):
            raise FliteError(f"flite spoke nothing for {request.text[:60]!r} with {request.voice!r}")
        settings = {"tempo": request.tempo, "pitch": _applied_pitch(request)}
        out.append(Utterance(request.text, f"flite:{request.voice}", audio, phonemes, settings))
    return out


def synthesize(text: str, voice: str = "slt", tempo: float = 1.0, pitch: float | None = None) -> Utterance:
    """Speak `text` with flite: audio at SAMPLE_RATE (float32) and its timed phonemes. `tempo` stretches durations
    (1.3: 1.3x longer); `pitch` is the target mean F0 in Hz (None: the voice's own; ignored by FIXED_PITCH)."""
    return synthesize_many([Request(text, voice, tempo, pitch)])[0]


__all__ = ["FIXED_PITCH", "FliteError", "RAND_SEED", "Request", "VOICES", "available", "synthesize", "synthesize_many"]
