"""Brief training of the demo speaker's Motion Translator on synthetic speech so its face moves with the audio.

Not the paper's training (EMOCA-tracked FLAME sequences of real speakers, InfoNCE-decoupled encoder, lip-reading
consistency): a stand-in that makes the demo speaker visibly talk across its whole expression basis. Targets per
video frame: jaw_pose[..., 0] (x-axis rotation opens the jaw) = the loudness-driven opening, and the expression
coefficients = a fixed hand-designed mix (`MOTION_MAP`) of the audio's motion signals (`audio.motion_signals`:
mouth opening, spread/round vowels, closure before onsets, fricatives, phrase emphasis and softness, blinks at
pauses, a slow warmth); docs/demo-speaker.md tabulates it.
Loss: the paper's reconstruction MSE over all parameters + its lip-motion smoothness term (frame differences).

Deterministic for a seed: clips and crops come from the seed (the initial weights are the caller's: build the
model after torch.manual_seed), and training stops at a fixed step count or a deterministic plateau test on a
fixed validation batch (docs/demo-speaker.md, "Identical builds"). `seconds_budget` is an optional wall-clock cap,
off by default: if it is what stops training, the result depends on the machine's speed (reported as stop_reason).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import torch

from gaussiantalker.sdk.progress import progress_bar

from ..export.speech import synth_speech
from ..model.translator import MotionTranslator
from .audio_signals import MOTION_SIGNALS, SAMPLE_RATE, jaw_target_from_audio, motion_signals
from .procedural_head import EXPRESSION_FIELDS

HELDOUT_SEED_OFFSET = 900_000  # held-out clip seed = this + seed: never one of the training clips' seeds
JAW_MAX_ANGLE = 0.3  # rad: jaw_pose x = this * the "open" signal (jaw_target_from_audio's default)
# Expression coefficient (a field of the demo head, head.EXPRESSION_FIELDS) = sum of weight * signal; every signal
# lies in [0, 1], so a coefficient stays within [0, sum of its weights] (<= 2.5). mouth_open = 4 * jaw angle, as
# before the full basis. blink 2.5 closes the eye over the iris (docs/demo-speaker.md).
MOTION_MAP = {
    "mouth_open": {"open": 4.0 * JAW_MAX_ANGLE},
    "smile": {"spread": 1.2, "warmth": 0.6},
    "pucker": {"round": 1.6},
    "funnel": {"round": 0.8, "fricative": 0.6},
    "lip_press": {"closure": 2.0},
    "upper_lip_raise": {"fricative": 1.2, "spread": 0.3},
    "lower_lip_depress": {"open": 0.5, "fricative": 0.8},
    "mouth_stretch": {"spread": 0.8, "open": 0.3},
    "corner_down": {"soft": 1.2},
    "chin_raise": {"closure": 0.8, "round": 0.4},
    "cheek_raise": {"warmth": 0.8, "spread": 0.4},
    "brow_raise": {"emphasis": 1.5},
    "brow_furrow": {"soft": 1.5},
    "blink_left": {"blink": 2.5},
    "blink_right": {"blink": 2.5},
}
# Coefficients past the named fields (the head's random local bumps) follow these signals in turn, weakly.
BUMP_SIGNALS = ("open", "round", "spread", "emphasis", "closure", "soft", "fricative")
BUMP_WEIGHT = 0.6
# Held-out correlation is reported per signal on the field it drives most (a prefix of the basis may lack some).
SIGNAL_FIELDS = {"open": "mouth_open", "spread": "smile", "round": "pucker", "closure": "lip_press",
                 "fricative": "upper_lip_raise", "emphasis": "brow_raise", "soft": "brow_furrow",
                 "blink": "blink_left", "warmth": "cheek_raise"}
# A coefficient "moves" on a clip when its range p95 - p5 is at least this: ~0.3 mm at its field's peak
# (EXPR_SIGMA_MM = 3 mm per unit), visible at the demo's portrait scale.
MOVING_RANGE = 0.1
# Effective dimension: singular values of the centred [T, n_expr] track above this fraction of the largest.
DIMENSION_RTOL = 0.01


@dataclass
class TrainSettings:
    """Knobs of the demo training run (its time and held-out correlation: docs/demo-speaker.md)."""

    max_steps: int = 400
    batch_size: int = 4
    crop_frames: int = 64  # 2.56 s crops: room for the slow signals' windows (emphasis, warmth, pauses)
    n_clips: int = 40
    clip_seconds: tuple[float, float] = (3.0, 6.0)  # at least crop_frames long
    lr: float = 2e-3
    warmup_steps: int = 30
    lambda_smooth: float = 1.0
    # Loss weight of jaw x: (mouth_open / jaw angle)^2 = 4^2, so the jaw's errors count as much as the mouth's
    # (its targets are 4x smaller than mouth_open's, so with weight 1 its errors barely count in the loss).
    jaw_weight: float = 16.0
    check_every: int = 50  # validation interval (steps) for the plateau test
    patience: int = 3  # stop after this many checks without a 2% validation improvement
    heldout_seconds: float = 8.0


def motion_matrix(n_expr: int) -> np.ndarray:
    """The fixed map [len(MOTION_SIGNALS), n_expr] from motion signals to expression coefficients (MOTION_MAP,
    then BUMP_SIGNALS in turn for coefficients past the named fields)."""
    matrix = np.zeros((len(MOTION_SIGNALS), n_expr), np.float32)
    for k in range(n_expr):
        drives = (MOTION_MAP[EXPRESSION_FIELDS[k]] if k < len(EXPRESSION_FIELDS)
                  else {BUMP_SIGNALS[(k - len(EXPRESSION_FIELDS)) % len(BUMP_SIGNALS)]: BUMP_WEIGHT})
        for signal, weight in drives.items():
            matrix[MOTION_SIGNALS.index(signal), k] = weight
    return matrix


def motion_targets(audio: np.ndarray, n_expr: int, samples_per_frame: int) -> np.ndarray:
    """Per-frame target parameters [T, n_expr + 3] (expression then jaw pose) derived from the audio alone."""
    signals = motion_signals(audio, fps=SAMPLE_RATE // samples_per_frame)
    target = np.zeros((signals.shape[0], n_expr + 3), dtype=np.float32)
    target[:, :n_expr] = signals @ motion_matrix(n_expr)
    target[:, n_expr] = JAW_MAX_ANGLE * signals[:, MOTION_SIGNALS.index("open")]  # = jaw_target_from_audio
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
        crop = settings.crop_frames
        if clip.size // spf < crop:
            raise ValueError(f"a training clip of {clip.size // spf} frames is shorter than crop_frames {crop}; "
                             "raise clip_seconds or lower crop_frames")
        start = int(rng.integers(clip.size // spf - crop + 1)) * spf
        piece = clip[start : start + crop * spf]
        audio.append(piece)
        targets.append(motion_targets(piece, n_expr, spf))
    return torch.from_numpy(np.stack(audio)), torch.from_numpy(np.stack(targets))


def motion_loss(pred: torch.Tensor, target: torch.Tensor, lambda_smooth: float,
                weights: torch.Tensor | None = None) -> torch.Tensor:
    """Paper §3.2 losses: MSE of the parameters + lambda * MSE of their frame-to-frame changes; `weights` [P]
    (default all 1) scales each parameter's squared errors."""
    w = torch.ones(pred.shape[-1], dtype=pred.dtype) if weights is None else weights
    reconstruction = torch.mean((pred - target) ** 2 * w)
    smoothness = torch.mean((torch.diff(pred, dim=1) - torch.diff(target, dim=1)) ** 2 * w)
    return reconstruction + lambda_smooth * smoothness


def parameter_weights(n_expr: int, settings: TrainSettings) -> torch.Tensor:
    """Loss weight per output [n_expr + 3]: 1, except jaw x (`settings.jaw_weight`)."""
    weights = torch.ones(n_expr + 3)
    weights[n_expr] = settings.jaw_weight
    return weights


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


def _evaluate(model: MotionTranslator, batch: tuple[torch.Tensor, torch.Tensor], lambda_smooth: float,
              weights: torch.Tensor) -> float:
    """Loss on a fixed batch without gradients (model in eval mode; there is no dropout, so it is the same)."""
    with torch.no_grad():
        return float(motion_loss(_predict(model, batch[0]), batch[1], lambda_smooth, weights))


def _pearson(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson r of two tracks; 0 when either is constant (no NaN)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.std() == 0 or b.std() == 0:
        return 0.0
    return float(np.corrcoef(a, b)[0, 1])


def moving_coefficients(expression: np.ndarray) -> int:
    """How many coefficients of a [T, n_expr] track move: range p95 - p5 >= MOVING_RANGE."""
    spread = np.percentile(expression, 95, axis=0) - np.percentile(expression, 5, axis=0)
    return int(np.sum(spread >= MOVING_RANGE))


def expression_dimension(expression: np.ndarray) -> int:
    """Effective dimension of a [T, n_expr] track: singular values of the centred track above DIMENSION_RTOL of
    the largest (0 for a still track)."""
    centred = np.asarray(expression, np.float64) - np.mean(expression, axis=0)
    sv = np.linalg.svd(centred, compute_uv=False) if centred.size else np.zeros(0)
    return int(np.sum(sv > DIMENSION_RTOL * sv[0])) if sv.size and sv[0] > 0 else 0


def heldout_clip(seed: int, seconds: float, spf: int) -> np.ndarray:
    """The unseen synthetic clip the held-out metrics use (whole video frames)."""
    frames = int(seconds * SAMPLE_RATE / spf)
    return synth_speech(frames * spf / SAMPLE_RATE, seed=HELDOUT_SEED_OFFSET + seed)[: frames * spf]


def heldout_jaw_correlation(model: MotionTranslator, seed: int, seconds: float = 8.0) -> float:
    """Pearson r between predicted jaw opening and the loudness target on an unseen synthetic clip."""
    return heldout_metrics(model, seed, seconds)["heldout_jaw_loudness_corr"]


def heldout_metrics(model: MotionTranslator, seed: int, seconds: float = 8.0) -> dict:
    """Metrics of the translator on an unseen synthetic clip: jaw/loudness r, moving coefficients, the
    predicted expression's effective dimension, and per-signal r between the predicted and target coefficient
    of the field the signal drives most (`heldout_corr_<signal>`; fields past n_expr are left out)."""
    spf = model.samples_per_frame
    audio = heldout_clip(seed, seconds, spf)
    target = motion_targets(audio, model.n_expr, spf)
    with torch.no_grad():
        expression, jaw_pose = (t[0].double().numpy() for t in model(torch.from_numpy(audio)[None]))
    metrics = {
        "heldout_jaw_loudness_corr": _pearson(jaw_pose[:, 0], jaw_target_from_audio(audio, fps=SAMPLE_RATE // spf)),
        "heldout_moving_coefficients": moving_coefficients(expression),
        "heldout_expression_dim": expression_dimension(expression),
        "target_moving_coefficients": moving_coefficients(target[:, : model.n_expr]),
        "target_expression_dim": expression_dimension(target[:, : model.n_expr]),
    }
    for signal, field in SIGNAL_FIELDS.items():
        k = EXPRESSION_FIELDS.index(field)
        if k < model.n_expr:
            metrics[f"heldout_corr_{signal}"] = _pearson(expression[:, k], target[:, k])
    return metrics


def train_demo_translator(
    model: MotionTranslator,
    n_expr: int,
    seconds_budget: float = math.inf,
    seed: int = 0,
    progress: bool = True,
    settings: TrainSettings | None = None,
) -> dict:
    """Train the translator in place on synthetic speech so its face follows the audio; returns metrics.

    Returns `heldout_metrics` (jaw/loudness r, moving coefficients, expression dimension, per-signal r) and
    "train_seconds", "steps", "final_loss", "initial_loss", "stop_reason"; the losses are on a fixed validation
    batch of training crops, before and after training.
    """
    if n_expr != model.n_expr:
        raise ValueError(f"n_expr {n_expr} does not match the translator's {model.n_expr}")
    settings = settings or TrainSettings()
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(2)  # the same float reductions on every machine: the same demo speaker everywhere
    try:
        return _train(model, n_expr, seconds_budget, seed, progress, settings)
    finally:
        torch.set_num_threads(previous_threads)


def _train(model: MotionTranslator, n_expr: int, seconds_budget: float, seed: int, progress: bool,
           settings: TrainSettings) -> dict:
    """The training loop of `train_demo_translator`, at the thread count it set."""
    torch.manual_seed(seed)
    spf = model.samples_per_frame
    clips = make_training_clips(settings.n_clips, settings.clip_seconds, seed, spf)
    rng = np.random.default_rng(seed)
    validation = sample_batch(clips, n_expr, settings, np.random.default_rng(seed + 1), spf)
    weights = parameter_weights(n_expr, settings)
    optimizer = torch.optim.Adam(model.parameters(), lr=settings.lr)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda s: _lr_factor(s, settings))
    model.eval()  # no dropout/batch-norm anywhere: train and eval behave the same
    initial_loss = best = _evaluate(model, validation, settings.lambda_smooth, weights)
    stale, step, stop_reason, start = 0, 0, "max_steps", time.perf_counter()
    bar = progress_bar(total=settings.max_steps, desc="translator", disable=not progress, leave=False)
    while step < settings.max_steps:
        if time.perf_counter() - start > seconds_budget:
            stop_reason = "time_budget"
            break
        audio, target = sample_batch(clips, n_expr, settings, rng, spf)
        loss = motion_loss(_predict(model, audio), target, settings.lambda_smooth, weights)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        optimizer.step()
        scheduler.step()
        step += 1
        bar.update(1)
        bar.set_postfix(loss=f"{loss.item():.4g}")
        if step % settings.check_every == 0:
            current = _evaluate(model, validation, settings.lambda_smooth, weights)
            stale = 0 if current < 0.98 * best else stale + 1
            best = min(best, current)
            if stale >= settings.patience:
                stop_reason = "converged"
                break
    bar.close()
    seconds = time.perf_counter() - start
    return {
        **heldout_metrics(model, seed, settings.heldout_seconds),
        "train_seconds": seconds,
        "steps": step,
        "final_loss": _evaluate(model, validation, settings.lambda_smooth, weights),
        "initial_loss": initial_loss,
        "stop_reason": stop_reason,
    }
