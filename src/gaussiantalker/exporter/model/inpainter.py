"""The inpainting generator F: fills holes the rendered face leaves inside the facial mask and smooths its contour.

The runtime composites I = (1 - M)·I_ori + M·F(x) with x = I_gau + (1 - M)·I_ori, on a crop around the mask's
bounding box. F works at half resolution (its five input channels average-pooled by 2): a small U-Net predicts a
fill colour and a blend weight w, both are upsampled bilinearly, and F(x) = clamp(x + w·(fill - x), 0, 1), so where
w ≈ 0 the rendered face keeps its full-resolution detail.

Both predictions are residuals on parameter-free priors, so an untrained F is already a sensible inpainter and
training only refines it: the w logit is W_LOGIT_BIAS (w ≈ 0.007) plus HOLE_LOGIT inside holes (the part of the
mask the render does not cover, w ≈ 0.99 there), and the fill is a push-pull interpolation of the visible colours
around each hole (covered pixels and everything outside the mask). The network's head starts at zero.

Crop sides must be multiples of CROP_MULTIPLE (the pool and up to three stride-2 levels halve them four times):
the torch module raises ValueError otherwise; the ONNX graph has no such check and onnxruntime fails on most other
sizes (mismatched skip shapes), so callers check with `crop_multiple_ok` first.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, fields

import numpy as np
import torch
import torch.nn.functional as nnf
from torch import nn

from gaussiantalker.sdk.progress import progress_bar

CROP_MULTIPLE = 16  # 2 (input pool) * 2**MAX_LEVELS (stride-2 levels)
MAX_LEVELS = 3
W_LOGIT_BIAS = -5.0  # w logit on covered pixels at init: sigmoid(-5) ≈ 0.0067, so F starts as nearly the identity
HOLE_LOGIT = 10.0  # added inside holes: sigmoid(-5 + 10) ≈ 0.993, so the fill prior shows there from the start
INPUT_RANGE = (-1.0, 2.0)  # inputs are clamped into this range first: nothing overflows for any finite input
PRIOR_MIN_WEIGHT = 1e-3  # push-pull guard: a crop with no visible pixel gets a black prior, not 0/0
PRIOR_CLAMP = 1e-3  # the fill prior is clamped to [this, 1 - this] before its logit (finite at 0 and 1)
LEAKY_SLOPE = 0.1
OUTSIDE_MASK_WEIGHT = 0.1  # loss weight of pixels outside the mask (the composite discards F's output there)


@dataclass(frozen=True)
class InpainterConfig:
    """Widths of the generator: `channels` at half resolution and twice that at each of the `levels` (1..3)
    stride-2 steps below it."""

    channels: int = 16
    levels: int = 3

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise ValueError(f"inpaint config field {f.name!r} must be an integer, got {value!r}")
            if value < 1:
                raise ValueError(f"inpaint config field {f.name!r} must be positive, got {value}")
        if self.levels > MAX_LEVELS:
            raise ValueError(f"inpaint config field 'levels' must be at most {MAX_LEVELS} (crops are multiples of "
                             f"{CROP_MULTIPLE}), got {self.levels}")

    def to_dict(self) -> dict:
        """Plain dict for bundle metadata."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> InpainterConfig:
        """Inverse of to_dict; ValueError naming the field on unknown keys, non-integers or out-of-range values."""
        unknown = sorted(set(data) - {f.name for f in fields(cls)})
        if unknown:
            raise ValueError(f"unknown inpaint config keys: {unknown}")
        config = cls(**data)
        return cls(**{name: int(value) for name, value in asdict(config).items()})  # numpy integers -> int


def crop_multiple_ok(height: int, width: int) -> bool:
    """Whether a crop of this size can go through F (both sides positive multiples of CROP_MULTIPLE)."""
    return height > 0 and width > 0 and height % CROP_MULTIPLE == 0 and width % CROP_MULTIPLE == 0


def _sanitize(x: torch.Tensor) -> torch.Tensor:
    """NaN -> 0, then clamp into INPUT_RANGE (which also takes ±inf); cheaper in onnxruntime than nan_to_num
    (docs/compositing.md, "The inpainting generator F").
    NaN is found as x != x: MNN has no IsNaN operator, and the comparison is the same test in every backend."""
    return torch.where(x == x, x, 0.0).clamp(*INPUT_RANGE)


def _half(x: torch.Tensor) -> torch.Tensor:
    """2x2 average pool of an even-sized map, written as a bilinear 0.5x resize (identical values; faster in
    onnxruntime: docs/compositing.md). Sizes rather than scale factors: the same graph, exported twice as fast."""
    return nnf.interpolate(x, size=(x.shape[2] // 2, x.shape[3] // 2), mode="bilinear", align_corners=False)


def _double(x: torch.Tensor) -> torch.Tensor:
    """Bilinear 2x upsampling (half-pixel centres)."""
    return nnf.interpolate(x, size=(x.shape[2] * 2, x.shape[3] * 2), mode="bilinear", align_corners=False)


def push_pull(colour: torch.Tensor, valid: torch.Tensor, levels: int) -> torch.Tensor:
    """Fill each pixel's colour from valid pixels nearby: weighted pyramid down `levels` times plus a global mean,
    then back up, each level keeping its own valid colour and taking the coarser one where it lacks weight.

    colour [B, 3, h, w] premultiplied by valid [B, 1, h, w] (both in [0, 1]); returns the unpremultiplied filled
    colour [B, 3, h, w] (0 where no pixel of the crop is valid).
    """
    pyramid = [torch.cat([colour, valid], dim=1)]
    for _ in range(levels):
        pyramid.append(_half(pyramid[-1]))
    pulled = pyramid[-1].mean(dim=(2, 3), keepdim=True)
    for i in reversed(range(len(pyramid))):
        coarse = pulled if i == len(pyramid) - 1 else _double(pulled)
        pulled = pyramid[i] + (1.0 - pyramid[i][:, 3:]) * coarse
    return pulled[:, :3] / pulled[:, 3:].clamp_min(PRIOR_MIN_WEIGHT)


def _conv(c_in: int, c_out: int, stride: int = 1) -> nn.Sequential:
    """3x3 convolution + LeakyReLU (padding 1: stride 1 keeps the size, stride 2 halves an even one)."""
    conv = nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1)
    # He init for the LeakyReLU: trains faster here than torch's default (which shrinks activations per layer).
    nn.init.kaiming_normal_(conv.weight, a=LEAKY_SLOPE, nonlinearity="leaky_relu")
    nn.init.zeros_(conv.bias)
    return nn.Sequential(conv, nn.LeakyReLU(LEAKY_SLOPE))


class InpainterNet(nn.Module):
    """F(image, mask, coverage) -> inpainted image, all [B, ·, H, W] float32 with H and W multiples of 16."""

    def __init__(self, config: InpainterConfig = InpainterConfig()):
        super().__init__()
        self.config = config
        widths = [config.channels * min(2 ** i, 2) for i in range(config.levels + 1)]
        self.stem = _conv(5, widths[0])
        self.down = nn.ModuleList(_conv(widths[i], widths[i + 1], stride=2) for i in range(config.levels))
        # Level i + 1 back to level i: 1x1 conv to level i's width (at the low resolution, where it is cheap),
        # nearest x2, add level i's skip, 3x3 conv.
        self.lateral = nn.ModuleList(nn.Conv2d(widths[i + 1], widths[i], 1) for i in range(config.levels))
        self.up = nn.ModuleList(_conv(widths[i], widths[i]) for i in range(config.levels))
        self.head = nn.Conv2d(widths[0], 4, 1)  # residual logits: fill colour (3) and blend weight w (1)
        nn.init.zeros_(self.head.weight)  # F starts as exactly its priors; gradients reach the weights at once
        nn.init.zeros_(self.head.bias)

    def forward(self, image: torch.Tensor, mask: torch.Tensor, coverage: torch.Tensor) -> torch.Tensor:
        height, width = image.shape[-2:]
        if height % CROP_MULTIPLE != 0 or width % CROP_MULTIPLE != 0:
            raise ValueError(f"inpaint crop {height}x{width} is not a multiple of {CROP_MULTIPLE} on both sides; "
                             f"pad or grow the crop")
        full = _sanitize(torch.cat([image, mask, coverage], dim=1))
        image = full[:, :3]
        hole = full[:, 3:4].clamp(0.0, 1.0) * (1.0 - full[:, 4:5].clamp(0.0, 1.0))  # mask the render leaves bare
        x = _half(full)
        # x is already premultiplied by validity: black in holes, the render's premultiplied colour where it
        # partly covers, the original frame outside the mask. Pooling it directly keeps hole edges from darkening.
        hole_half = x[:, 3:4].clamp(0.0, 1.0) * (1.0 - x[:, 4:5].clamp(0.0, 1.0))
        prior = push_pull(x[:, :3].clamp(0.0, 1.0), 1.0 - hole_half, self.config.levels)
        prior = prior.clamp(PRIOR_CLAMP, 1.0 - PRIOR_CLAMP)

        features = [self.stem(x)]
        for down in self.down:
            features.append(down(features[-1]))
        y = features[-1]
        for i in reversed(range(len(self.up))):
            y = self.up[i](nnf.interpolate(self.lateral[i](y), scale_factor=2.0, mode="nearest") + features[i])
        logits = self.head(y)

        fill = _double(torch.sigmoid(logits[:, :3] + torch.log(prior / (1.0 - prior))))
        # The hole term is added at full resolution, so holes are filled right up to their edges.
        weight = torch.sigmoid(_double(logits[:, 3:]) + (W_LOGIT_BIAS + HOLE_LOGIT * hole))
        return (image + weight * (fill - image)).clamp(0.0, 1.0)


def count_parameters(model: nn.Module) -> int:
    """Number of trainable scalars."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def masked_l1(output: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean |output - target| weighted by the mask, OUTSIDE_MASK_WEIGHT outside it (bounded, never 0/0)."""
    weight = mask.clamp(0.0, 1.0) * (1.0 - OUTSIDE_MASK_WEIGHT) + OUTSIDE_MASK_WEIGHT
    return (weight * (output - target).abs()).sum() / (weight.sum() * output.shape[1])


def train_inpainter(model: InpainterNet,
                  batch: Callable[[np.random.Generator],
                                  tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]],
                  *, seconds: float = 60.0, max_steps: int | None = None, seed: int = 0, lr: float = 3e-3,
                  progress: bool = False) -> list[float]:
    """Adam on the mask-weighted L1 to `batch(rng)`'s targets until `seconds` pass or `max_steps` are done.

    `batch` returns (image, mask, coverage, target); its rng is seeded with `seed`, as is torch (the initial
    weights are the caller's). Returns the loss of every step; the model is left in eval mode.
    """
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    optimizer = torch.optim.Adam(model.parameters(), lr=lr)
    losses: list[float] = []
    model.train()
    start = time.perf_counter()
    with progress_bar(total=max_steps, disable=not progress, desc="inpaint", unit="step") as bar:
        while (max_steps is None or len(losses) < max_steps) and time.perf_counter() - start < seconds:
            image, mask, coverage, target = batch(rng)
            loss = masked_l1(model(image, mask, coverage), target, mask)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            nn.utils.clip_grad_norm_(model.parameters(), 1.0)
            optimizer.step()
            losses.append(float(loss.detach()))
            if not math.isfinite(losses[-1]):
                raise FloatingPointError(f"inpaint training loss became {losses[-1]} at step {len(losses)}")
            bar.update(1)
            bar.set_postfix(loss=f"{losses[-1]:.4f}")
    model.eval()
    return losses
