"""Speech with its phone timings from festival (docs/voice.md, "Voices"), run as a subprocess: English voices, and
Italian, Czech, Finnish and Catalan ones (their phone sets in phonesets.py).

One `festival -b script.scm` process speaks a whole batch (start-up costs ~0.2 s): the script selects each
request's voice afresh (so one request's settings never reach the next), speaks its text, and writes the wave and a
listing of its tokens and segments (phone, end time from the Segment relation, syllable stress, token) to a
temporary folder read back here. Text reaches festival only inside Scheme string literals of that script, with
backslashes and double quotes escaped and control characters made spaces; never on a command line.

Voices (Debian packages): `slt_hts` (festvox-us-slt-hts, an HMM voice: 32 kHz; its tempo is the HTS engine's
speed "-r", which also times the segments; festival 2.5's HTS module reads only "-m" and "-r" of its parameters,
so its pitch cannot be set and `pitch` is ignored), `kal` and `ked` (festvox-kallpc16k, festvox-kdlpc16k: LPC
diphone voices at 16 kHz; tempo is `Duration_Stretch`, pitch the target mean F0 of `int_lr_params`). The other
languages' voices (WORLD_VOICES) take their tempo the same way (`ona`, an HTS voice, through "-r") and keep their
own pitch: their intonation modules read no target F0 (measured: the same F0 at 90 and 200 Hz asked).

festival reads its script as bytes, and each language's voices read text in their own charset (Czech in
ISO-8859-2, the others in Latin-1): a request's lines are written in its voice's charset and its listing read back
in it. English voices keep UTF-8, as before these voices came.

Deterministic (tests/test_voice_synths.py): the same request gives the same samples in any batch, after any other
request, in any process. Timing, measured on a few sentences: segments are ARPAbet phones, so a voiceless stop's
segment holds its closure, burst and aspiration; it starts where the vowel before it begins to fade, the energy
falls steepest a median 17 ms (slt_hts), 21 ms (kal), 8 ms (ked) after its start and is 16-31 dB below the vowel's
10-20 ms into it (a noise floor, not digital silence); the burst comes at ~60-80 % of it. Lips closing at the
segment's start thus close about half a frame early. Vowel onsets after nasals and fricatives lie a median 4-9 ms
after the segment boundary (HTS durations come in 5 ms frames).
"""

from __future__ import annotations

import shutil
import subprocess
import tempfile
import threading
import wave
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gaussiantalker.sdk.audio import resample

from .arpabet import is_silence
from .espeak import SAMPLE_RATE, Utterance
from .phonesets import CATALAN, CZECH, FINNISH, ITALIAN, PhoneSet
from .segments import Request, Row, clean_text, phonemes_of, request_problem


@dataclass(frozen=True)
class Voice:
    """A festival voice: its function, Debian package, the language of its text, the charset it reads that text in
    and its phone set (None: ARPAbet); an HTS voice takes its tempo through the engine's speed."""

    function: str
    package: str
    language: str = "en"
    charset: str = "utf-8"
    phones: PhoneSet | None = None
    hts: bool = False
    fixed_pitch: bool = False
    settings: str = ""  # Scheme run after selecting the voice, before each request


# festival's Czech voices draw pause lengths (and more) from libc's rand(), whose state runs on from request to request:
# off, every draw is its range's middle, so a request's audio is its own (module docstring).
_CZECH_FIXED = "(set! czech-randomize nil)"
ENGLISH_VOICES: dict[str, Voice] = {
    "slt_hts": Voice("voice_cmu_us_slt_arctic_hts", "festvox-us-slt-hts", hts=True, fixed_pitch=True),
    "kal": Voice("voice_kal_diphone", "festvox-kallpc16k"),
    "ked": Voice("voice_ked_diphone", "festvox-kdlpc16k"),
}
WORLD_VOICES: dict[str, Voice] = {
    "lp": Voice("voice_lp_diphone", "festvox-italp16k", "it", "latin-1", ITALIAN, fixed_pitch=True),  # woman
    "pc": Voice("voice_pc_diphone", "festvox-itapc16k", "it", "latin-1", ITALIAN, fixed_pitch=True),  # man
    "dita": Voice("voice_czech_dita", "festvox-czech-dita", "cs", "iso-8859-2", CZECH, fixed_pitch=True,
                  settings=_CZECH_FIXED),  # woman
    "krb": Voice("voice_czech_krb", "festvox-czech-krb", "cs", "iso-8859-2", CZECH, fixed_pitch=True,
                 settings=_CZECH_FIXED),  # a boy
    "machac": Voice("voice_czech_machac", "festvox-czech-machac", "cs", "iso-8859-2", CZECH, fixed_pitch=True,
                    settings=_CZECH_FIXED),  # man
    "ph": Voice("voice_czech_ph", "festvox-czech-ph", "cs", "iso-8859-2", CZECH, fixed_pitch=True,
                settings=_CZECH_FIXED),  # man
    "lj": Voice("voice_suo_fi_lj_diphone", "festvox-suopuhe-lj", "fi", "latin-1", FINNISH, fixed_pitch=True),
    "mv": Voice("voice_hy_fi_mv_diphone", "festvox-suopuhe-mv", "fi", "latin-1", FINNISH, fixed_pitch=True),
    "ona": Voice("voice_upc_ca_ona_hts", "festvox-ca-ona-hts", "ca", "latin-1", CATALAN, hts=True,
                 fixed_pitch=True),  # woman
}
VOICE_TABLE: dict[str, Voice] = {**ENGLISH_VOICES, **WORLD_VOICES}
VOICES: dict[str, str] = {name: voice.function for name, voice in VOICE_TABLE.items()}
HTS_VOICES = frozenset(name for name, voice in VOICE_TABLE.items() if voice.hts)  # tempo: the module docstring
FIXED_PITCH = frozenset(name for name, voice in VOICE_TABLE.items() if voice.fixed_pitch)  # `pitch` is ignored
CHUNK = 200  # requests per festival process
TIMEOUT_S = (30.0, 5.0)  # a process's limit: the first + the second per request

# Speaks one request: a listing of its top-level tokens (T name) and segments (S name end stress token), the token
# numbered from 1 (0: none, a pause), then its wave when it has segments. unwind-protect turns an error into a
# missing file (and the script goes on with the next request).
_PRELUDE = """
(define (gt_say text wav listing)
  (let ((utt (SynthText text)) (fd nil) (token nil) (i 0))
    (set! fd (fopen listing "w"))
    (set! token (utt.relation.first utt 'Token))
    (while token
      (set! i (+ i 1))
      (item.set_feat token "gt_index" i)
      (format fd "T %s\\n" (item.name token))
      (set! token (item.next token)))
    (mapcar
      (lambda (s)
        (format fd "S %s %f %s %s\\n" (item.name s) (item.feat s "end") (item.feat s "R:SylStructure.parent.stress")
                (item.feat s "R:SylStructure.parent.parent.R:Token.parent.gt_index")))
      (utt.relation.items utt 'Segment))
    (fclose fd)
    (if (utt.relation.first utt 'Segment) (utt.save.wave utt wav 'riff))))
"""


class FestivalError(RuntimeError):
    """festival is missing, lacks a voice, or could not speak a request."""


_lock = threading.Lock()
_installed: dict[str, frozenset[str]] = {}


def _program() -> str:
    program = shutil.which("festival")
    if program is None:
        raise FestivalError("festival is not installed (Debian: apt-get install festival)")
    return program


def _installed_voices() -> frozenset[str]:
    """Festival's voice names here (`voice.list`), asked once per process."""
    with _lock:
        if "voices" not in _installed:
            with tempfile.TemporaryDirectory(prefix="gt-festival-") as folder:
                script = Path(folder) / "voices.scm"
                script.write_text('(format t "%l\\n" (voice.list))\n', encoding="utf-8")
                done = subprocess.run([_program(), "-b", str(script)], capture_output=True, timeout=60,
                                      stdin=subprocess.DEVNULL, cwd=folder)
            names = done.stdout.decode("utf-8", "replace").strip().strip("()").split()
            _installed["voices"] = frozenset(names)
        return _installed["voices"]


def available(voice: str | None = None) -> bool:
    """Whether festival runs here (and has `voice`, one of VOICES, installed)."""
    try:
        _check_voice(voice or next(iter(VOICES)), any_voice=voice is None)
        return True
    except FestivalError:
        return False


def _check_voice(voice: str, any_voice: bool = False) -> None:
    if voice not in VOICES:
        raise FestivalError(f"festival has no voice {voice!r} here (known: {', '.join(VOICES)})")
    installed = _installed_voices()
    if any_voice:
        return
    if VOICES[voice].removeprefix("voice_") not in installed:
        raise FestivalError(f"festival's voice {voice!r} ({VOICES[voice]}) is not installed "
                            f"(Debian: apt-get install {VOICE_TABLE[voice].package})")


def scheme_string(text: str) -> str:
    """`text` as a Scheme string literal: backslash and double quote escaped, control characters made spaces."""
    return '"' + clean_text(text).replace("\\", "\\\\").replace('"', '\\"') + '"'


def _validate(request: Request) -> None:
    _check_voice(request.voice)
    problem = request_problem(request)
    if problem:
        raise FestivalError(f"festival: {problem}")


def _applied_pitch(request: Request) -> float | None:
    return None if request.voice in FIXED_PITCH else request.pitch


def _request_scheme(request: Request, wav: Path, listing: Path) -> str:
    """The script's lines for one request: its voice afresh, its tempo and pitch, then `gt_say`."""
    voice = VOICE_TABLE[request.voice]
    lines = [f"({voice.function})"] + ([voice.settings] if voice.settings else [])
    if request.voice in HTS_VOICES:
        lines.append("(Parameter.set 'Duration_Stretch 1.0)")
        speed = 1.0 / request.tempo  # the engine's speech speed: 0.77 speaks 1.3x longer
        lines.append(f'(set! hts_engine_params (append hts_engine_params (list (list "-r" {speed:.6f}))))')
    else:
        lines.append(f"(Parameter.set 'Duration_Stretch {request.tempo:.6f})")
        pitch = _applied_pitch(request)
        if pitch is not None:  # int_lr reads the first target_f0_mean of the list
            lines.append(f"(set! int_lr_params (cons (list 'target_f0_mean {pitch:.3f}) int_lr_params))")
    lines.append(f"(unwind-protect (gt_say {scheme_string(request.text)} {scheme_string(str(wav))} "
                 f"{scheme_string(str(listing))}) nil)")
    return "\n".join(lines) + "\n"


def _read_wave(path: Path) -> np.ndarray:
    """A 16-bit mono RIFF wave -> float32 at SAMPLE_RATE."""
    with wave.open(str(path), "rb") as handle:
        rate, width, channels = handle.getframerate(), handle.getsampwidth(), handle.getnchannels()
        pcm = np.frombuffer(handle.readframes(handle.getnframes()), "<i2")
    if width != 2 or channels != 1:
        raise FestivalError(f"festival wrote {path.name} as {channels} channels of {width} bytes, not 16-bit mono")
    return resample(pcm.astype(np.float32) / 32768.0, rate, SAMPLE_RATE).astype(np.float32)


def _read_listing(path: Path, charset: str = "utf-8") -> tuple[list[str], list[Row]]:
    tokens: list[str] = []
    rows: list[Row] = []
    for line in path.read_bytes().decode(charset, "replace").splitlines():
        if line.startswith("T "):
            tokens.append(line[2:])
        elif line.startswith("S "):
            name, end, stress, token = line[2:].split()
            index = int(float(token))
            rows.append(Row(name, float(end), int(float(stress)), index - 1 if index > 0 else None))
    return tokens, rows


class Unspoken(FestivalError):
    """festival could not speak one request (an error inside its synthesis, or no segments)."""


def _utterance(request: Request, wav: Path, listing: Path, log: str) -> Utterance:
    if not listing.exists():
        raise Unspoken(f"festival could not speak {request.text[:60]!r} with {request.voice!r}: "
                       f"{log.strip()[-400:] or 'it stopped without a message'}")
    voice = VOICE_TABLE[request.voice]
    tokens, rows = _read_listing(listing, voice.charset)
    silence = is_silence if voice.phones is None else voice.phones.is_silence
    if not any(not silence(row.name) for row in rows) or not wav.exists():
        raise Unspoken(f"festival spoke nothing for {request.text[:60]!r} with {request.voice!r}")
    audio = _read_wave(wav)
    try:
        phonemes = phonemes_of(rows, tokens, request.text, audio.shape[0] / SAMPLE_RATE, voice.phones)
    except ValueError as exc:
        raise FestivalError(f"festival spoke {request.text[:60]!r} with a phone it should not: {exc}") from exc
    settings = {"tempo": request.tempo, "pitch": _applied_pitch(request)}
    return Utterance(request.text, f"festival:{request.voice}", audio, phonemes, settings)


def _spoken_or_none(request: Request, wav: Path, listing: Path, log: str, skip_failed: bool) -> Utterance | None:
    try:
        return _utterance(request, wav, listing, log)
    except Unspoken:
        if skip_failed:
            return None
        raise


def _run(requests: Sequence[Request], skip_failed: bool = False) -> list[Utterance | None]:
    """Speak requests in one festival process (None for one it could not speak, where `skip_failed`)."""
    with tempfile.TemporaryDirectory(prefix="gt-festival-") as name:
        folder = Path(name)
        paths = [(folder / f"{k}.wav", folder / f"{k}.txt") for k in range(len(requests))]
        script = _PRELUDE.encode("ascii") + b"".join(
            _request_scheme(r, w, t).encode(VOICE_TABLE[r.voice].charset, errors="replace")
            for r, (w, t) in zip(requests, paths, strict=True))
        (folder / "speak.scm").write_bytes(script)
        timeout = TIMEOUT_S[0] + TIMEOUT_S[1] * len(requests)
        try:
            done = subprocess.run([_program(), "-b", str(folder / "speak.scm")], capture_output=True, timeout=timeout,
                                  stdin=subprocess.DEVNULL, cwd=folder)
        except subprocess.TimeoutExpired as exc:
            raise FestivalError(f"festival took over {timeout:.0f} s for {len(requests)} requests") from exc
        log = (done.stdout + done.stderr).decode("utf-8", "replace")
        if done.returncode != 0:
            log += f"\n(festival exited with code {done.returncode}{': it crashed' if done.returncode < 0 else ''})"
        return [_spoken_or_none(r, w, t, log, skip_failed) for r, (w, t) in zip(requests, paths, strict=True)]


def synthesize_many(requests: Sequence[Request], chunk: int = CHUNK, workers: int = 1,
                    skip_failed: bool = False) -> list[Utterance | None]:
    """Speak every request (in order): CHUNK per festival process, `workers` processes at once. Each utterance
    depends on its own request only (module docstring). A request festival cannot speak is an error naming it, or
    with `skip_failed` None in its place: the Italian voices' intonation fails on a few random sentences (a Scheme
    type error inside SynthText), the same ones every time."""
    requests = list(requests)
    for request in requests:
        _validate(request)
    chunks = [requests[k:k + chunk] for k in range(0, len(requests), max(1, chunk))]
    with ThreadPoolExecutor(max(1, workers)) as pool:
        return [u for spoken in pool.map(lambda part: _run(part, skip_failed), chunks) for u in spoken]


def synthesize(text: str, voice: str = "slt_hts", tempo: float = 1.0, pitch: float | None = None) -> Utterance:
    """Speak `text` with festival: audio at SAMPLE_RATE (float32) and its timed phonemes. `tempo` stretches
    durations (1.3: 1.3x longer); `pitch` is the target mean F0 in Hz (None: the voice's own; FIXED_PITCH voices
    ignore it)."""
    return synthesize_many([Request(text, voice, tempo, pitch)])[0]


__all__ = ["ENGLISH_VOICES", "FIXED_PITCH", "FestivalError", "HTS_VOICES", "Request", "Unspoken", "VOICES",
           "VOICE_TABLE", "Voice", "WORLD_VOICES", "available", "scheme_string", "synthesize", "synthesize_many"]
