"""Training the demo speaker's inpainting generator F on its procedural clip (docs/compositing.md, "Demo clip").

A training pair is a clip frame re-rendered with another jaw: F's input is that render pasted into the original
frame by the formula's x = I_gau + (1 - M) I_ori, its target the frame the clip would have held with that jaw
(the demo clip's composer draws both). F is fully convolutional, so it trains on patches: most centred on the
mask's edge, where it has to fill and blend, the rest anywhere in the crop, where it must leave the face alone.

Deterministic for a seed: the pairs, the patches and F's initial weights come from the seed, torch runs on a fixed
thread count, and training stops after a fixed number of steps, never on the wall clock (docs/demo-speaker.md,
"Identical builds").
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import torch

from gaussiantalker.runtime.composite import crop_box
from gaussiantalker.sdk.image import to_uint8
from gaussiantalker.sdk.progress import progress_bar

from ..model.inpainter import InpainterNet, train_inpainter
from .clip import JAW_OPEN_MAX, ClipComposer
from .steps import INPAINT_STEPS, training_steps

PATCH = 96  # training patch side (a multiple of the generator's CROP_MULTIPLE)
BATCH = 8
EDGE_FRACTION = 0.75  # share of patches centred on the mask's edge
NEW_JAW_MAX = 1.2 * JAW_OPEN_MAX  # re-rendered jaws range a little past the clip's own


@dataclass
class InpainterPair:
    """One training pair on the frame's crop, stored 8-bit: x, target [h, w, 3]; mask, coverage [h, w]."""

    x: np.ndarray
    target: np.ndarray
    mask: np.ndarray
    coverage: np.ndarray
    edge: np.ndarray  # [k, 2] rows, columns of mask-edge pixels (0 < M < 1), patch centres


def make_pair(composer: ClipComposer, index: int, jaw: float) -> InpainterPair:
    """Clip frame `index` re-rendered with `jaw` (radians): F's input and target on the mask's crop."""
    original, _ = composer.frame(index)
    head = composer.render_head(composer.drive(index, jaw))
    target = composer.compose(index, head).image
    picture = to_uint8(original.image).astype(np.float32) / 255.0  # the clip as stored: 8-bit
    mask = original.mask
    x = head[..., :3] + (1.0 - mask[..., None]) * picture
    box = crop_box(mask)
    crop = (box.rows, box.columns)
    edge = np.argwhere((mask[crop] > 0.0) & (mask[crop] < 1.0))
    return InpainterPair(to_uint8(x[crop]), to_uint8(target[crop]), to_uint8(mask[crop]),
                       to_uint8(head[..., 3][crop]), edge)


def _patch(pair: InpainterPair, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    height, width = pair.mask.shape
    if pair.edge.size and rng.random() < EDGE_FRACTION:
        cy, cx = pair.edge[rng.integers(len(pair.edge))]
    else:
        cy, cx = rng.integers(height), rng.integers(width)
    top = int(np.clip(cy - PATCH // 2, 0, height - PATCH))
    left = int(np.clip(cx - PATCH // 2, 0, width - PATCH))
    window = (slice(top, top + PATCH), slice(left, left + PATCH))
    return pair.x[window], pair.mask[window], pair.coverage[window], pair.target[window]


def batch_sampler(pairs: list[InpainterPair]):
    """`train_inpainter`'s batch source: BATCH random patches of random pairs, as float tensors in [0, 1]."""

    def batch(rng: np.random.Generator) -> tuple[torch.Tensor, ...]:
        patches = [_patch(pairs[rng.integers(len(pairs))], rng) for _ in range(BATCH)]
        x, mask, coverage, target = (np.stack(parts).astype(np.float32) / 255.0 for parts in zip(*patches, strict=True))
        return (torch.from_numpy(x).permute(0, 3, 1, 2), torch.from_numpy(mask)[:, None],
                torch.from_numpy(coverage)[:, None], torch.from_numpy(target).permute(0, 3, 1, 2))

    return batch


PAIRS = 96  # training pairs for a full training (FULL_PAIRS_STEPS or more)
FULL_PAIRS_STEPS = 300
MIN_PAIRS = 16
TORCH_THREADS = 2  # a fixed thread count: the same float reductions however many cores the machine has


def pairs_for(steps: int) -> int:
    """Training pairs worth rendering for a training of `steps`: PAIRS from FULL_PAIRS_STEPS up, proportionally
    fewer below (at least MIN_PAIRS). Each pair costs two renders, ~0.3 s at the clip's size; a brief training (a
    test's or CI's) draws too few patches to use them all."""
    return max(MIN_PAIRS, min(PAIRS, round(PAIRS * steps / FULL_PAIRS_STEPS)))


def train_demo_inpainter(composer: ClipComposer, *, pairs: int | None = None, steps: int | None = None,
                         seconds: float | None = None, seed: int = 0, progress: bool = True
                         ) -> tuple[InpainterNet, dict]:
    """Render `pairs` training pairs (default: `pairs_for(steps)`), then train F for `steps` (default INPAINT_STEPS;
    `seconds`, the former time budget, is read as a step count: exporter/demo/steps.py); returns F and its
    training metrics. The same seed and steps give the same F."""
    steps = training_steps(steps, seconds, INPAINT_STEPS, names=("steps", "seconds"))
    if steps < 1:
        raise ValueError("training F takes at least one step")
    pairs = pairs_for(steps) if pairs is None else pairs
    rng = np.random.default_rng(seed)
    count = len(composer.track)
    start = time.perf_counter()
    data = [make_pair(composer, int(rng.integers(count)), float(rng.uniform(0.0, NEW_JAW_MAX)))
            for _ in progress_bar(range(pairs), desc="inpaint pairs", unit="pair", disable=not progress)]
    render_seconds = time.perf_counter() - start
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(TORCH_THREADS)
    try:
        torch.manual_seed(seed)  # F's initial weights, whatever ran before
        model = InpainterNet()
        losses = train_inpainter(model, batch_sampler(data), seconds=math.inf, max_steps=steps, seed=seed,
                                 progress=progress)
    finally:
        torch.set_num_threads(previous_threads)
    head = float(np.mean(losses[:20])) if losses else float("nan")
    tail = float(np.mean(losses[-20:])) if losses else float("nan")
    return model.eval(), {"inpaint_pairs": pairs, "inpaint_pair_seconds": round(render_seconds, 1),
                          "inpaint_steps": len(losses), "inpaint_loss_first": round(head, 5),
                          "inpaint_loss_last": round(tail, 5)}
