"""Training streams: espeak-ng utterances joined by silences of random length, with their ARKit targets, and the
augmented crops the network learns from (docs/voice.md, "Training data").

Utterances are joined into streams of ~STREAM_SECONDS so the network sees speech begin and end after pauses of
every length (and blinks at them); targets are computed on the whole stream, from its phonemes shifted onto the
stream's timeline. A crop is then made harder than a synthesiser's clean studio voice: speed perturbation (tempo
and pitch, the targets stretched with it), a short room reverb, a first-order tilt of the spectrum (a dull or a
bright microphone), noise at 15-45 dB SNR, the channel of a call (telephone, Opus, a band-limited headset:
channels.py) and a random gain (-30..+6 dB). Everything random comes from the numpy generator the caller passes:
the same seed, the same crops.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import wave
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gaussiantalker.runtime.translate import resample_rows
from gaussiantalker.sdk.audio import write_wav
from gaussiantalker.sdk.progress import progress_bar

from . import channels, espeak
from .corpus import Spec
from .espeak import PAUSE, Phoneme, Utterance, phonemes_from_json
from .targets import arkit_targets, frame_count

SPEAK_CHUNK, SPEAK_WORKERS = 100, 2  # utterances per worker process, processes at once
STREAM_SECONDS = 30.0
GAP_S = (0.0, 0.9)  # silence between two utterances of a stream
LEAD_S = 0.3  # silence before a stream's first utterance
SAMPLE_RATE = espeak.SAMPLE_RATE
GAIN_DB = (-30.0, 6.0)
TILT = (-0.7, 0.9)  # y[n] = x[n] - a x[n-1]
NOISE_P, NOISE_SNR_DB = 0.5, (15.0, 45.0)
REVERB_P, REVERB_RT60_S = 0.3, (0.1, 0.4)
SPEED_P, SPEED = 0.3, (0.88, 1.12)
# A call's channel, drawn in CHANNEL_P of the crops: (name, share of those crops).
CHANNEL_P = 0.35
CHANNEL_KINDS = (("telephone", 0.3), ("opus", 0.4), ("low_pass", 0.3))
OPUS_KBPS, LOW_PASS_HZ = (6.0, 24.0), (3500.0, 7000.0)


@dataclass
class Stream:
    """One training stream: audio [S] at SAMPLE_RATE and its targets [frames, 52] at 25 fps."""

    audio: np.ndarray
    targets: np.ndarray


def _speak_chunk(specs: list[Spec]) -> list[Utterance]:
    """Synthesise specs in order (run in a fresh worker process: see `speak`), each by its engine."""
    from . import festival, flite  # imported in the worker only: flite's library loads with the module's first use
    from .corpus import HELDOUT_FAMILY, TRAIN_FAMILIES, VOICE_LANGUAGES, WORLD_FAMILY

    own_pitch = {(engine, voice): hz for engine, voices in [*TRAIN_FAMILIES.values(), HELDOUT_FAMILY[1:],
                                                            WORLD_FAMILY[1:]]
                 for voice, hz in voices.items()}
    out: list[Utterance] = []
    k = 0
    while k < len(specs):  # a run of one engine's specs at a time, so festival speaks a run in one process
        engine = specs[k].engine
        run = [specs[k]]
        while k + len(run) < len(specs) and specs[k + len(run)].engine == engine:
            run.append(specs[k + len(run)])
        if engine == "espeak":
            out += [espeak.synthesize(s.text, s.voice, s.rate, s.pitch, s.pitch_range, s.word_gap) for s in run]
        else:
            module = {"festival": festival, "flite": flite}[engine]
            requests = [festival.Request(s.text, s.voice, s.tempo, s.pitch_hz(own_pitch[(engine, s.voice)]))
                        for s in run]
            if engine == "festival" and any(s.voice in VOICE_LANGUAGES for s in run):
                # the other languages' voices fail on a few sentences (festival.synthesize_many): left out, counted
                # by `speak`'s caller as the specs without an utterance
                out += [u for u in module.synthesize_many(requests, skip_failed=True) if u is not None]
            else:
                out += module.synthesize_many(requests)
        k += len(run)
    return out


def speak(specs: list[Spec], progress: bool = True, desc: str = "espeak-ng", chunk: int = SPEAK_CHUNK
          ) -> list[Utterance]:
    """Synthesise every spec, CHUNK at a time, each chunk in a fresh process (two at once).

    Why fresh processes: espeak-ng 1.51 carries state from one utterance to the next, and late in a long run in one
    process a few utterances came out differently from run to run (6 of 1,400 after the 1,250th, measured);
    starting each chunk from a new library makes the audio a function of the chunk alone (and flite's reseeding of
    libc's rand() never reaches espeak-ng)."""
    bar = progress_bar(total=len(specs), desc=desc, disable=not progress, leave=False)
    chunks = [specs[k:k + chunk] for k in range(0, len(specs), chunk)]
    out: list[Utterance] = []
    context = multiprocessing.get_context("spawn")
    with context.Pool(SPEAK_WORKERS, maxtasksperchild=1) as pool:
        for spoken in pool.imap(_speak_chunk, chunks):
            out += spoken
            bar.update(len(spoken))
    bar.close()
    return out


def join(utterances: list[Utterance], gaps: list[float]) -> tuple[np.ndarray, list[Phoneme], str]:
    """Utterances on one timeline: LEAD_S of silence, then each utterance followed by its gap (a pause)."""
    pieces = [np.zeros(int(LEAD_S * SAMPLE_RATE), np.float32)]
    phonemes = [Phoneme(PAUSE, 0.0, LEAD_S)]
    text, at = "", LEAD_S
    for utterance, gap in zip(utterances, gaps, strict=True):
        offset = len(text)
        phonemes += [Phoneme(p.ipa, p.start + at, p.end + at, p.stress, p.text_position + offset)
                     for p in utterance.phonemes]
        text += utterance.text + " "
        at += utterance.seconds
        silence = int(round(gap * SAMPLE_RATE))
        pieces += [utterance.audio, np.zeros(silence, np.float32)]
        if silence:
            phonemes.append(Phoneme(PAUSE, at, at + silence / SAMPLE_RATE, 0, len(text)))
        at += silence / SAMPLE_RATE
    return np.concatenate(pieces), phonemes, text


def make_streams(utterances: list[Utterance], rng: np.random.Generator) -> list[Stream]:
    """Utterances in order, grouped into streams of ~STREAM_SECONDS with random gaps; targets per stream."""
    streams, group, seconds = [], [], 0.0
    for k, utterance in enumerate(utterances):
        group.append(utterance)
        seconds += utterance.seconds
        if seconds >= STREAM_SECONDS or k == len(utterances) - 1:
            gaps = [float(rng.uniform(*GAP_S)) for _ in group]
            audio, phonemes, text = join(group, gaps)
            frames = frame_count(audio.shape[0] / SAMPLE_RATE)
            audio = np.pad(audio, (0, frames * 640 - audio.shape[0]))
            streams.append(Stream(audio, arkit_targets(phonemes, text, audio)))
            group, seconds = [], 0.0
    return streams


def crop(streams: list[Stream], frames: int, rng: np.random.Generator, span: int | None = None
         ) -> tuple[np.ndarray, np.ndarray]:
    """A random crop of `span` frames (default `frames`): (audio [span * 640], targets [span, 52]), streams drawn
    by length."""
    span = frames if span is None else span
    lengths = np.array([s.targets.shape[0] - span + 1 for s in streams], np.float64)
    if lengths.max() < 1:
        raise ValueError(f"no stream holds {span} frames")
    stream = streams[int(rng.choice(len(streams), p=np.maximum(lengths, 0) / np.maximum(lengths, 0).sum()))]
    start = int(rng.integers(stream.targets.shape[0] - span + 1))
    return stream.audio[start * 640:(start + span) * 640].copy(), stream.targets[start:start + span]


def sped_crop(streams: list[Stream], frames: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A crop of `frames` frames, in SPEED_P of the draws played faster or slower (SPEED): a longer or shorter
    span of the stream squeezed into `frames` frames of audio, its targets resampled with it."""
    if rng.random() >= SPEED_P:
        return crop(streams, frames, rng)
    factor = float(rng.uniform(*SPEED))
    audio, targets = crop(streams, frames, rng, span=max(1, int(round(frames * factor))))
    factor = targets.shape[0] / frames  # the span's whole frames set the exact factor
    sped = channels.speed(audio, factor)
    sped = np.pad(sped, (0, max(0, frames * 640 - sped.size)))[: frames * 640]
    return sped.astype(np.float32), resample_rows(targets, frames).astype(np.float32)


def _convolve(x: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """x * kernel, cut to x's length (by FFT: a room tail is thousands of taps)."""
    size = 1 << int(np.ceil(np.log2(x.size + kernel.size)))
    return np.fft.irfft(np.fft.rfft(x, size) * np.fft.rfft(kernel, size), size)[: x.size]


def augment(audio: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A harder copy of clean speech: reverb, tilt, noise, a call's channel, gain (module docstring), clipped to
    +-1."""
    x = audio.astype(np.float64)
    speech_rms = np.sqrt(np.mean(x * x)) + 1e-9
    if rng.random() < REVERB_P:
        rt60 = rng.uniform(*REVERB_RT60_S)
        n = int(rt60 * SAMPLE_RATE)
        tail = rng.standard_normal(n) * np.exp(-6.9 * np.arange(n) / n)  # -60 dB at rt60
        tail *= rng.uniform(0.05, 0.3) / np.sqrt(np.sum(tail * tail))
        x = x + _convolve(x, tail)
    tilt = rng.uniform(*TILT)
    x = x - tilt * np.concatenate([[0.0], x[:-1]])
    x *= speech_rms / (np.sqrt(np.mean(x * x)) + 1e-9)
    if rng.random() < NOISE_P:
        noise = rng.standard_normal(x.size)
        if rng.random() < 0.5:  # brown-ish: most of its energy low, as room and fan noise
            noise = np.cumsum(noise)
            running = np.cumsum(np.concatenate([[0.0], noise]))
            noise -= np.interp(np.arange(noise.size), np.arange(200, noise.size - 200),
                               (running[401:] - running[:-401]) / 401) if noise.size > 401 else noise.mean()
        noise *= speech_rms / (np.sqrt(np.mean(noise * noise)) + 1e-9) * 10 ** (-rng.uniform(*NOISE_SNR_DB) / 20)
        x = x + noise
    if rng.random() < CHANNEL_P:
        x = call_channel(x.astype(np.float32), rng).astype(np.float64)
    x *= 10 ** (rng.uniform(*GAIN_DB) / 20)
    return np.clip(x, -1.0, 1.0).astype(np.float32)


def call_channel(x: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One of CHANNEL_KINDS, drawn by its share, at a random bit rate or cut-off."""
    names, shares = zip(*CHANNEL_KINDS, strict=True)
    kind = names[int(rng.choice(len(names), p=np.array(shares) / sum(shares)))]
    if kind == "telephone":
        return channels.telephone(x)
    if kind == "opus":
        return channels.opus(x, float(rng.uniform(*OPUS_KBPS)))
    return channels.low_pass(x, float(rng.uniform(*LOW_PASS_HZ)))


def batch(streams: list[Stream], count: int, frames: int, rng: np.random.Generator, augmented: bool = True
          ) -> tuple[np.ndarray, np.ndarray]:
    """(audio [count, frames * 640], targets [count, frames, 52])."""
    audio, targets = [], []
    for _ in range(count):
        a, t = sped_crop(streams, frames, rng) if augmented else crop(streams, frames, rng)
        audio.append(augment(a, rng) if augmented else a)
        targets.append(t)
    return np.stack(audio), np.stack(targets)


def save_utterance(utterance: Utterance, stem: str | os.PathLike) -> None:
    """`stem`.wav (16-bit PCM at SAMPLE_RATE) and `stem`.json (text, voice, settings, timed phonemes)."""
    stem = Path(stem)
    write_wav(stem.with_suffix(".wav"), utterance.audio, SAMPLE_RATE)
    stem.with_suffix(".json").write_text(json.dumps(utterance.to_json(), indent=1, ensure_ascii=False) + "\n",
                                         encoding="utf-8")


def load_utterance(stem: str | os.PathLike) -> Utterance:
    """What `save_utterance` wrote (the WAV read with the standard library: no ffmpeg needed)."""
    stem = Path(stem)
    meta = json.loads(stem.with_suffix(".json").read_text(encoding="utf-8"))
    with wave.open(str(stem.with_suffix(".wav")), "rb") as handle:
        if handle.getnchannels() != 1 or handle.getsampwidth() != 2 or handle.getframerate() != SAMPLE_RATE:
            raise ValueError(f"{stem}.wav is not 16-bit mono PCM at {SAMPLE_RATE} Hz")
        pcm = np.frombuffer(handle.readframes(handle.getnframes()), "<i2")
    return Utterance(meta["text"], meta["voice"], pcm.astype(np.float32) / 32768.0, phonemes_from_json(meta),
                     meta.get("settings", {}))


__all__ = ["Stream", "augment", "batch", "call_channel", "crop", "join", "load_utterance", "make_streams",
           "save_utterance", "speak", "sped_crop"]
