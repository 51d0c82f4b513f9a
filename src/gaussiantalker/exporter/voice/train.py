"""Training the voice network on espeak-ng speech with phoneme-derived ARKit targets (docs/voice.md, "Training").

Deterministic for a seed on a given machine: the sentences, voices, gaps, crops and augmentations come from numpy
generators seeded from it, the initial weights from torch.manual_seed(seed), training runs a fixed number of
steps (never a time budget) at a fixed thread count, and nothing else is random. A run given a `resume` file saves
its whole state there as it goes and, killed and started again, continues to the same weights.
Loss: a weighted mean squared error of the 52 weights (CHANNEL_WEIGHTS: the mouth counts most, the closure and
the jaw most of all) plus VELOCITY_WEIGHT times that of their frame-to-frame changes, plus closure_weight times
the lips' excess opening where the targets close them for a /p b m/, over each crop's frames after its first
CONTEXT_FRAMES (those lack the past the network reads). Each crop's log-mel bands may be warped as another vocal
tract's (`warp_voices`).
"""

from __future__ import annotations

import hashlib
import os
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from gaussiantalker.sdk.progress import progress_bar
from gaussiantalker.sdk.rig import ARKIT_BLENDSHAPES, ARKIT_COUNT

from .corpus import family_specs, training_specs, world_specs
from .data import Stream, batch, make_streams, speak
from .model import VoiceConfig, VoiceNet, check_receptive_field, count_parameters, mel_warp

# One thread: the same float reductions on every machine, and on a busy machine two threads of one op wait on
# each other (docs/voice.md, "Training").
THREADS = 1
CONTEXT_FRAMES = 8
VELOCITY_WEIGHT = 0.5
# Lips left open where the targets close them for a /p b m/ (the lips' aperture jawOpen - mouthClose above the
# target's, on frames whose target aperture is at most CLOSED_APERTURE and whose target press is at least
# PRESSED: a bilabial's, not a pause's rest): the near-misses the closure measure counts, weighted apart
# (TrainSettings.closure_weight). On every closed frame, pauses included, it closed the mouth everywhere (vowels too).
CLOSED_APERTURE, PRESSED = 0.05, 0.1
JAW, CLOSE = ARKIT_BLENDSHAPES.index("jawOpen"), ARKIT_BLENDSHAPES.index("mouthClose")
PRESS = ARKIT_BLENDSHAPES.index("mouthPressLeft")
# Vocal tract length perturbation of a crop's log-mel bands (model.mel_warp): share of crops, factor range.
WARP_P, WARP_FACTOR = 0.6, (0.86, 1.16)
# Frequency masks on a crop's log-mel bands (SpecAugment's): masks per masked crop and the widest, in bands; each
# masked span takes the crop's mean level, so no band can be relied on alone (TrainSettings.band_masks: the share
# of crops masked).
MASKS, MASK_WIDTH = 2, 8
# A smooth random colour over the log-mel bands, a voice's and a microphone's (TrainSettings.band_colour: the share
# of crops coloured): a sum of COLOUR_TERMS cosines over the bands whose largest gain is COLOUR_GAIN (log-mel units:
# ln(power) x LOG_SCALE, so 0.35 is 6 dB).
COLOUR_TERMS, COLOUR_GAIN = 3, 0.35
# Loss weight per ARKit channel (others 1; channels the targets never move 0.2, so they learn to stay at 0).
CHANNEL_WEIGHTS = {"jawOpen": 4.0, "mouthClose": 4.0, "mouthPressLeft": 2.0, "mouthPressRight": 2.0,
                   "mouthPucker": 2.0, "mouthFunnel": 2.0, "mouthRollLower": 2.0, "mouthRollUpper": 2.0,
                   "mouthSmileLeft": 1.5, "mouthSmileRight": 1.5, "mouthStretchLeft": 1.5,
                   "mouthStretchRight": 1.5, "browInnerUp": 0.5, "browOuterUpLeft": 0.5, "browOuterUpRight": 0.5}
MOVING = ("jaw", "mouth", "tongue", "eyeBlink", "browInnerUp", "browOuterUp")


@dataclass
class TrainSettings:
    """Knobs of a training run (the committed model's: docs/voice.md)."""

    steps: int = 5000
    batch_size: int = 12
    crop_frames: int = 100
    utterances: int = 1400
    natural_utterances: int = 1800  # English ones by festival's and flite's voices (corpus.TRAIN_FAMILIES)
    world_utterances: int = 0  # Italian, Czech, Finnish and Catalan ones by festival's voices (corpus.WORLD_FAMILY)
    lr: float = 2e-3
    warmup_steps: int = 100
    final_lr_share: float = 0.05
    weight_decay: float = 1e-4
    channels: int = 128
    closure_weight: float = 3.0  # of the closure term (voice_loss)
    band_masks: float = 0.0  # share of crops whose log-mel bands are masked (mask_bands)
    band_colour: float = 0.0  # share of crops whose log-mel bands are coloured (colour_bands)


def channel_weights() -> torch.Tensor:
    """Loss weight per ARKit channel [52]."""
    weights = [CHANNEL_WEIGHTS.get(name, 1.0 if name.startswith(MOVING) else 0.2) for name in ARKIT_BLENDSHAPES]
    return torch.tensor(weights, dtype=torch.float32)


def voice_loss(pred: torch.Tensor, target: torch.Tensor, weights: torch.Tensor, closure_weight: float = 3.0
               ) -> torch.Tensor:
    """Weighted MSE of the weights and of their frame-to-frame changes, plus `closure_weight` times the squared
    excess aperture where the targets close the lips for a /p b m/ (frames after CONTEXT_FRAMES)."""
    pred, target = pred[:, CONTEXT_FRAMES:], target[:, CONTEXT_FRAMES:]
    value = torch.mean((pred - target) ** 2 * weights)
    velocity = torch.mean((torch.diff(pred, dim=1) - torch.diff(target, dim=1)) ** 2 * weights)
    target_aperture = target[..., JAW] - target[..., CLOSE]
    excess = torch.relu(pred[..., JAW] - pred[..., CLOSE] - target_aperture)
    closed = ((target_aperture <= CLOSED_APERTURE) & (target[..., PRESS] >= PRESSED)).to(pred.dtype)
    closure = torch.sum(excess ** 2 * closed) / torch.clamp(torch.sum(closed), min=1.0)
    return value + VELOCITY_WEIGHT * velocity + closure_weight * closure


def warp_voices(features: torch.Tensor, rng: np.random.Generator) -> torch.Tensor:
    """Each crop's log-mel bands [B, N_MELS, S] as another vocal tract's in WARP_P of the crops (a factor drawn
    log-uniformly from WARP_FACTOR): more speakers than the synthesisers have."""
    out = features.clone()
    for k in range(features.shape[0]):
        if rng.random() < WARP_P:
            factor = float(np.exp(rng.uniform(*np.log(WARP_FACTOR))))
            out[k] = torch.from_numpy(mel_warp(factor)) @ features[k]
    return out


def mask_bands(features: torch.Tensor, rng: np.random.Generator, share: float) -> torch.Tensor:
    """Each crop's log-mel bands [B, N_MELS, S] with MASKS spans of up to MASK_WIDTH bands set to the crop's mean
    level, in `share` of the crops (no draw at all for share 0: a run without masks is the run before them)."""
    if share <= 0:
        return features
    out = features.clone()
    bands = features.shape[1]
    for k in range(features.shape[0]):
        if rng.random() < share:
            level = features[k].mean()
            for _ in range(MASKS):
                width = int(rng.integers(1, MASK_WIDTH + 1))
                first = int(rng.integers(0, bands - width + 1))
                out[k, first:first + width] = level
    return out


def colour_bands(features: torch.Tensor, rng: np.random.Generator, share: float) -> torch.Tensor:
    """Each crop's log-mel bands [B, N_MELS, S] plus a smooth random curve over the bands (COLOUR_TERMS cosines,
    at most COLOUR_GAIN), in `share` of the crops (no draw for share 0)."""
    if share <= 0:
        return features
    out = features.clone()
    position = np.linspace(0.0, np.pi, features.shape[1])
    for k in range(features.shape[0]):
        if rng.random() < share:
            cycles = rng.uniform(0.5, 3.0, COLOUR_TERMS)
            phases = rng.uniform(0.0, 2 * np.pi, COLOUR_TERMS)
            amplitudes = rng.uniform(-1.0, 1.0, COLOUR_TERMS)
            curve = (amplitudes[:, None] * np.cos(cycles[:, None] * position[None] + phases[:, None])).sum(0)
            curve *= COLOUR_GAIN / max(float(np.abs(curve).max()), 1e-6)
            out[k] += torch.from_numpy(curve.astype(np.float32))[:, None]
    return out


def _lr_factor(step: int, settings: TrainSettings) -> float:
    """Linear warm-up, then a cosine down to final_lr_share of the base rate."""
    if step < settings.warmup_steps:
        return (step + 1) / settings.warmup_steps
    progress = min(1.0, (step - settings.warmup_steps) / max(1, settings.steps - settings.warmup_steps))
    share = settings.final_lr_share
    return share + (1.0 - share) * 0.5 * (1.0 + np.cos(np.pi * progress))


def training_streams(settings: TrainSettings, seed: int, progress: bool = True) -> list[Stream]:
    """The training streams of a seed: its sentences spoken and joined (other engines' utterances grouped by
    voice, so a stream is one speaker's, as a call is)."""
    natural = sorted(family_specs(settings.natural_utterances, seed) + world_specs(settings.world_utterances, seed),
                     key=lambda s: (s.engine, s.voice))
    specs = training_specs(settings.utterances, seed) + natural
    utterances = speak(specs, progress, desc="speaking")
    if len(utterances) < len(specs):  # other languages' sentences festival could not speak (data._speak_chunk)
        print(f"training: festival could not speak {len(specs) - len(utterances)} of {settings.world_utterances} "
              "sentences of its other languages' voices; trained without them", file=sys.stderr)
    return make_streams(utterances, np.random.default_rng([seed, 1]))


def train(streams: list[Stream], settings: TrainSettings | None = None, seed: int = 0, progress: bool = True,
          resume: str | os.PathLike | None = None, resume_every: int = 250) -> tuple[VoiceNet, dict]:
    """Train a new network on `streams` for settings.steps steps; returns it and the run's record.

    `resume`: a file where the run's whole state (weights, optimiser, schedule, data generator, losses) is saved
    every `resume_every` steps and read back at the start when it holds a state of the same settings and seed, so a
    killed run goes on where it was and ends with the same weights as an uninterrupted one."""
    settings = settings or TrainSettings()
    previous = torch.get_num_threads()
    torch.set_num_threads(THREADS)
    try:
        return _train(streams, settings, seed, progress, None if resume is None else Path(resume), resume_every)
    finally:
        torch.set_num_threads(previous)


def fingerprint(streams: list[Stream]) -> str:
    """A digest of the training streams (audio and targets): a saved state resumes only on the same data."""
    digest = hashlib.sha256()
    for stream in streams:
        digest.update(stream.audio.tobytes())
        digest.update(stream.targets.tobytes())
    return digest.hexdigest()


def _save_state(path: Path, state: dict) -> None:
    """Write through a temporary file, so a run killed while saving keeps its previous state."""
    partial = path.with_name(path.name + ".partial")
    torch.save(state, partial)
    partial.replace(path)


def _train(streams: list[Stream], settings: TrainSettings, seed: int, progress: bool, resume: Path | None,
           resume_every: int) -> tuple[VoiceNet, dict]:
    torch.manual_seed(seed)
    config = VoiceConfig(channels=settings.channels, outputs=ARKIT_COUNT)
    check_receptive_field(config)
    model = VoiceNet(config)
    rng = np.random.default_rng([seed, 2])
    weights = channel_weights()
    optimizer = torch.optim.AdamW(model.parameters(), lr=settings.lr, weight_decay=settings.weight_decay)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda s: _lr_factor(s, settings))
    losses: list[float] = []
    key = {"settings": asdict(settings), "seed": seed, "data": fingerprint(streams)}
    if resume is not None and resume.is_file():
        state = torch.load(resume, weights_only=False)  # our own file, written below
        if state.get("key") == key:
            model.load_state_dict(state["model"])
            optimizer.load_state_dict(state["optimizer"])
            scheduler.load_state_dict(state["scheduler"])
            rng.bit_generator.state = state["rng"]
            losses = list(state["losses"])
    bar = progress_bar(total=settings.steps, initial=len(losses), desc="training", disable=not progress,
                       leave=False)
    start = time.perf_counter()
    for step in range(len(losses), settings.steps):
        audio, target = batch(streams, settings.batch_size, settings.crop_frames, rng)
        with torch.no_grad():
            features = warp_voices(model.features(torch.from_numpy(audio)), rng)
            features = colour_bands(mask_bands(features, rng, settings.band_masks), rng, settings.band_colour)
        loss = voice_loss(model.forward_features(features), torch.from_numpy(target), weights,
                          settings.closure_weight)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        optimizer.step()
        scheduler.step()
        losses.append(float(loss.detach()))
        bar.update(1)
        bar.set_postfix(loss=f"{np.mean(losses[-50:]):.4g}")
        if resume is not None and ((step + 1) % resume_every == 0 or step + 1 == settings.steps):
            _save_state(resume, {"key": key, "model": model.state_dict(), "optimizer": optimizer.state_dict(),
                                 "scheduler": scheduler.state_dict(), "rng": rng.bit_generator.state,
                                 "losses": losses})
    bar.close()
    model.eval()
    record = {"settings": asdict(settings), "seed": seed, "data": key["data"][:16], "config": config.to_dict(),
              "parameters": count_parameters(model), "steps": settings.steps,
              "loss_first_50": float(np.mean(losses[:50])), "loss_last_50": float(np.mean(losses[-50:])),
              "train_seconds": round(time.perf_counter() - start, 1)}
    return model, record


__all__ = ["CHANNEL_WEIGHTS", "TrainSettings", "channel_weights", "colour_bands", "mask_bands", "train",
           "training_streams", "voice_loss", "warp_voices"]
