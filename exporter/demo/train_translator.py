"""Brief training of the demo speaker's Motion Translator on synthetic speech so its jaw follows loudness.

Not the paper's training (EMOCA-tracked FLAME sequences of real speakers, InfoNCE-decoupled encoder, lip-reading
consistency): a stand-in that makes the demo speaker visibly talk. Targets per video frame, from
`audio.py`: jaw_pose[..., 0] (x-axis rotation opens the jaw) = loudness-driven opening, expression[..., 0]
(mouth opening) = a scaled copy, expression[..., 1] = slow spectral tilt (fricative vs vowel), all else 0.
Loss: the paper's reconstruction MSE over all parameters + its lip-motion smoothness term (frame differences).

Deterministic for a seed: clips and crops come from the seed (the initial weights are the caller's: build the
model after torch.manual_seed), and training stops at a fixed step count or a deterministic plateau test on a
fixed validation batch. `seconds_budget` is only a safety cap:
if it is what stops training, the result depends on the machine's speed (reported as stop_reason).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from gaussiantalker.sdk.progress import progress_bar

from ..export.speech import synth_speech
from ..model.translator import MotionTranslator
from .audio import SAMPLE_RATE, jaw_target_from_audio, smooth_frames, spectral_tilt

MOUTH_EXPR_GAIN = 4.0  # expression[..., 0] = MOUTH_EXPR_GAIN * jaw opening (rad): up to ~1.2 at full opening
TILT_EXPR_GAIN = 0.5  # expression[..., 1] = TILT_EXPR_GAIN * slowly smoothed spectral tilt in (-1, 1)
HELDOUT_SEED_OFFSET = 900_000  # held-out clip seed = this + seed: never one of the training clips' seeds


@dataclass
class TrainSettings:
    """Knobs of the demo training run (its time and held-out correlation: docs/demo-speaker.md)."""

    max_steps: int = 200
    batch_size: int = 4
    crop_frames: int = 40  # 1.6 s crops
    n_clips: int = 40
    clip_seconds: tuple[float, float] = (2.0, 4.0)
    lr: float = 2e-3
    warmup_steps: int = 30
    lambda_smooth: float = 1.0
    check_every: int = 50  # validation interval (steps) for the plateau test
    patience: int = 3  # stop after this many checks without a 2% validation improvement
    heldout_seconds: float = 8.0


def motion_targets(audio: np.ndarray, n_expr: int, samples_per_frame: int) -> np.ndarray:
    """Per-frame target parameters [T, n_expr + 3] (expression then jaw pose) derived from the audio alone."""
    fps = SAMPLE_RATE // samples_per_frame
    jaw_open = jaw_target_from_audio(audio, fps=fps)
    target = np.zeros((jaw_open.size, n_expr + 3), dtype=np.float32)
    target[:, 0] = MOUTH_EXPR_GAIN * jaw_open
    if n_expr > 1:
        target[:, 1] = TILT_EXPR_GAIN * smooth_frames(spectral_tilt(audio, fps=fps), 9)
    target[:, n_expr] = jaw_open
    return target


def make_training_clips(n_clips: int, seconds: tuple[float, float], seed: int, spf: int) -> list[np.ndarray]:
    """Synthesise the training clips (lengths whole video frames), reproducibly from the seed."""
    rng = np.random.default_rng(seed)
    clips = []
    for i in range(n_clips):
        frames = int(rng.uniform(*seconds) * SAMPLE_RATE / spf)
        clips.append(synth_speech(frames * spf / SAMPLE_RATE, seed=100_000 + 1000 * seed + i)[: frames * spf])
    return clips


def sample_batch(
    clips: list[np.ndarray], n_expr: int, settings: TrainSettings, rng: np.random.Generator, spf: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Random crops (audio [B, S], targets [B, T, n_expr + 3]); targets are computed on each crop itself."""
    audio, targets = [], []
    for _ in range(settings.batch_size):
        clip = clips[int(rng.integers(len(clips)))]
        crop = min(settings.crop_frames, clip.size // spf)
        start = int(rng.integers(clip.size // spf - crop + 1)) * spf
        piece = clip[start : start + crop * spf]
        audio.append(piece)
        targets.append(motion_targets(piece, n_expr, spf))
    return torch.from_numpy(np.stack(audio)), torch.from_numpy(np.stack(targets))


def motion_loss(pred: torch.Tensor, target: torch.Tensor, lambda_smooth: float) -> torch.Tensor:
    """Paper §3.2 losses: MSE of the parameters + lambda * MSE of their frame-to-frame changes."""
    reconstruction = torch.mean((pred - target) ** 2)
    smoothness = torch.mean((torch.diff(pred, dim=1) - torch.diff(target, dim=1)) ** 2)
    return reconstruction + lambda_smooth * smoothness


def _predict(model: MotionTranslator, audio: torch.Tensor) -> torch.Tensor:
    """Model output as one tensor [B, T, n_expr + 3] (expression then jaw pose)."""
    expression, jaw_pose = model(audio)
    return torch.cat([expression, jaw_pose], dim=-1)


def _lr_factor(step: int, settings: TrainSettings) -> float:
    """Linear warm-up then cosine decay to 10% of the base learning rate."""
    if step < settings.warmup_steps:
        return (step + 1) / settings.warmup_steps
    progress = (step - settings.warmup_steps) / max(1, settings.max_steps - settings.warmup_steps)
    return 0.1 + 0.45 * (1.0 + np.cos(np.pi * min(1.0, progress)))


def _evaluate(model: MotionTranslator, batch: tuple[torch.Tensor, torch.Tensor], lambda_smooth: float) -> float:
    """Loss on a fixed batch without gradients (model in eval mode; there is no dropout, so it is the same)."""
    with torch.no_grad():
        return float(motion_loss(_predict(model, batch[0]), batch[1], lambda_smooth))


def heldout_jaw_correlation(model: MotionTranslator, seed: int, seconds: float = 8.0) -> float:
    """Pearson r between predicted jaw opening and the loudness target on an unseen synthetic clip."""
    spf = model.samples_per_frame
    frames = int(seconds * SAMPLE_RATE / spf)
    audio = synth_speech(frames * spf / SAMPLE_RATE, seed=HELDOUT_SEED_OFFSET + seed)[: frames * spf]
    target = jaw_target_from_audio(audio, fps=SAMPLE_RATE // spf).astype(np.float64)
    with torch.no_grad():
        _, jaw_pose = model(torch.from_numpy(audio)[None])
    predicted = jaw_pose[0, :, 0].double().numpy()
    if predicted.std() == 0 or target.std() == 0:
        return 0.0
    return float(np.corrcoef(predicted, target)[0, 1])


def train_demo_translator(
    model: MotionTranslator,
    n_expr: int,
    seconds_budget: float = 150,
    seed: int = 0,
    progress: bool = True,
    settings: TrainSettings | None = None,
) -> dict:
    """Train the translator in place on synthetic speech so the jaw follows loudness; returns metrics.

    Returns {"heldout_jaw_loudness_corr", "train_seconds", "steps", "final_loss", "initial_loss", "stop_reason"};
    the losses are on a fixed validation batch of training crops, before and after training.
    """
    if n_expr != model.n_expr:
        raise ValueError(f"n_expr {n_expr} does not match the translator's {model.n_expr}")
    settings = settings or TrainSettings()
    torch.manual_seed(seed)
    torch.set_num_threads(2)
    spf = model.samples_per_frame
    clips = make_training_clips(settings.n_clips, settings.clip_seconds, seed, spf)
    rng = np.random.default_rng(seed)
    validation = sample_batch(clips, n_expr, settings, np.random.default_rng(seed + 1), spf)
    optimizer = torch.optim.Adam(model.parameters(), lr=settings.lr)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda s: _lr_factor(s, settings))
    model.eval()  # no dropout/batch-norm anywhere: train and eval behave the same
    initial_loss = best = _evaluate(model, validation, settings.lambda_smooth)
    stale, step, stop_reason, start = 0, 0, "max_steps", time.perf_counter()
    bar = progress_bar(total=settings.max_steps, desc="translator", disable=not progress, leave=False)
    while step < settings.max_steps:
        if time.perf_counter() - start > seconds_budget:
            stop_reason = "time_budget"
            break
        audio, target = sample_batch(clips, n_expr, settings, rng, spf)
        loss = motion_loss(_predict(model, audio), target, settings.lambda_smooth)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        optimizer.step()
        scheduler.step()
        step += 1
        bar.update(1)
        bar.set_postfix(loss=f"{loss.item():.4g}")
        if step % settings.check_every == 0:
            current = _evaluate(model, validation, settings.lambda_smooth)
            stale = 0 if current < 0.98 * best else stale + 1
            best = min(best, current)
            if stale >= settings.patience:
                stop_reason = "converged"
                break
    bar.close()
    seconds = time.perf_counter() - start
    return {
        "heldout_jaw_loudness_corr": heldout_jaw_correlation(model, seed, settings.heldout_seconds),
        "train_seconds": seconds,
        "steps": step,
        "final_loss": _evaluate(model, validation, settings.lambda_smooth),
        "initial_loss": initial_loss,
        "stop_reason": stop_reason,
    }
