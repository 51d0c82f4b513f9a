"""The voice network: audio 16 kHz -> ARKit-52 weights at 25 fps, a small convolutional net with a bounded
receptive field (docs/voice.md, "The model").

    audio [B, S] ──► length fitted: T = max(1, round(S / 640)) frames, audio zero-padded or cut to T x 640,
                     then SILENCE_BEFORE frames of silence before it and SILENCE_AFTER after (dropped at the end)
                 ──► log-mel front end (fixed): 25 ms Hann windows every 10 ms as a Conv1d with a DFT basis, power,
                     64 mel bands (40 Hz - 7.6 kHz), log; [B, 64, 4T]
                 ──► a strided convolution: eight 10 ms steps (the frame's four and two on each side) -> one
                     25 fps step
                 ──► residual blocks at 25 fps (per-step channel norm, dilated convolution, 1x1 convolution)
                 ──► a causal convolution and a 1x1 head: [B, 52, T] -> [B, T, 52]

Why this shape: every layer is a convolution whose padding is split between past and future, so the output at a
frame depends on a fixed span of audio around it (RECEPTIVE_PAST_S before, RECEPTIVE_FUTURE_S after the frame):
a live session at 160 ms lookahead with 1 s of context (docs/live.md) then sees all the audio an offline pass
uses, and the runtime's overlapping windows agree on every frame they share. Audio beyond a window's ends is
silence (the silence padding covers the receptive field), as a live session's zero-filled history is: a clip's
first frames come out the same offline and live. No normalisation spans time (the
channel norm is per step), for the same reason; gain invariance is learned from level-augmented audio instead.
Only Conv, Mul, Add, Log, Sigmoid, ReduceMean, AveragePool, Pad, Slice and friends: the ONNX graph
(onnx_graph.py) is built by hand from these modules at opset 17.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from gaussiantalker.sdk.rig import ARKIT_COUNT

SAMPLE_RATE = 16000
FPS = 25
SAMPLES_PER_FRAME = SAMPLE_RATE // FPS  # 640
HOP = 160  # 10 ms: four front-end steps per video frame
WINDOW = 400  # 25 ms
N_BINS = WINDOW // 2 + 1
N_MELS = 64
FMIN, FMAX = 40.0, 7600.0
STEPS_PER_FRAME = SAMPLES_PER_FRAME // HOP
# Power floor of the log-mel (a Hann window of a full-scale sine has power ~(WINDOW/4)^2 = 1e4 in its bin):
# 1e-4 is ~100 dB below it, under any recording's noise floor.
LOG_FLOOR = 1e-4
LOG_SCALE = 0.25  # log-mel values / 4: the first convolution sees numbers near unit size
NORM_EPS = 1e-5
# The receptive field the live session must cover (checked by tests/test_voice.py by perturbing the audio).
RECEPTIVE_PAST_S = 1.0
RECEPTIVE_FUTURE_S = 0.16
# Frames of silence put before and after the audio (at least the receptive field), their outputs dropped.
SILENCE_BEFORE, SILENCE_AFTER = 22, 4


@dataclass(frozen=True)
class VoiceConfig:
    """Sizes of the network: channels and its residual blocks as (dilation, future taps 0 or 1)."""

    channels: int = 128
    blocks: tuple[tuple[int, int], ...] = ((1, 1), (2, 1), (4, 0), (1, 0), (2, 0), (1, 0))
    outputs: int = ARKIT_COUNT
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        data = asdict(self)
        data["blocks"] = [list(b) for b in self.blocks]
        return data


def hz_to_mel(hz: np.ndarray) -> np.ndarray:
    return 2595.0 * np.log10(1.0 + np.asarray(hz, np.float64) / 700.0)


def mel_to_hz(mel: np.ndarray) -> np.ndarray:
    return 700.0 * (10.0 ** (np.asarray(mel, np.float64) / 2595.0) - 1.0)


def mel_warp(factor: float) -> np.ndarray:
    """[N_MELS, N_MELS] linear map of log-mel bands to those of the same voice with its spectrum stretched by
    `factor` (a shorter or longer vocal tract: vocal tract length perturbation, docs/voice.md, "Augmentation"):
    band k takes the value at frequency centre_k / factor, interpolated between bands, the edge bands held."""
    centres = mel_to_hz(np.linspace(hz_to_mel(FMIN), hz_to_mel(FMAX), N_MELS + 2))[1:-1]
    position = np.interp(hz_to_mel(centres / factor), hz_to_mel(centres), np.arange(N_MELS))
    low = np.clip(np.floor(position).astype(int), 0, N_MELS - 1)
    high = np.minimum(low + 1, N_MELS - 1)
    share = position - low
    out = np.zeros((N_MELS, N_MELS))
    out[np.arange(N_MELS), low] += 1.0 - share
    out[np.arange(N_MELS), high] += share
    return out.astype(np.float32)


def mel_matrix() -> np.ndarray:
    """Triangular mel filters [N_MELS, N_BINS] (HTK mel scale, each filter's area normalised to 1 bin)."""
    freqs = np.arange(N_BINS) * SAMPLE_RATE / WINDOW
    edges = mel_to_hz(np.linspace(hz_to_mel(FMIN), hz_to_mel(FMAX), N_MELS + 2))
    out = np.zeros((N_MELS, N_BINS))
    for m in range(N_MELS):
        lo, mid, hi = edges[m], edges[m + 1], edges[m + 2]
        out[m] = np.clip(np.minimum((freqs - lo) / (mid - lo), (hi - freqs) / (hi - mid)), 0.0, None)
        out[m] /= max(out[m].sum(), 1e-9)
    return out.astype(np.float32)


def dft_basis() -> np.ndarray:
    """Hann-windowed DFT as a Conv1d weight [2 * N_BINS, 1, WINDOW]: real parts, then imaginary parts."""
    n = np.arange(WINDOW)
    window = 0.5 - 0.5 * np.cos(2.0 * np.pi * n / WINDOW)  # periodic Hann
    k = np.arange(N_BINS)[:, None]
    angle = 2.0 * np.pi * k * n[None, :] / WINDOW
    basis = np.concatenate([np.cos(angle) * window, -np.sin(angle) * window])
    return basis[:, None, :].astype(np.float32)


def frames_for(samples: int) -> int:
    """Video frames the model gives for `samples` of audio: round(S / 640), at least 1 (S a multiple of 640: exact)."""
    return max(1, (int(samples) + SAMPLES_PER_FRAME // 2) // SAMPLES_PER_FRAME)


def fit_length(audio: torch.Tensor) -> torch.Tensor:
    """[B, S] -> [B, frames_for(S) * 640]: zero-padded at the end or cut."""
    length = frames_for(audio.shape[-1]) * SAMPLES_PER_FRAME
    if audio.shape[-1] >= length:
        return audio[..., :length]
    return F.pad(audio, (0, length - audio.shape[-1]))


class FrontEnd(nn.Module):
    """Fixed log-mel features: [B, S] (S a multiple of HOP) -> [B, N_MELS, S / HOP]; step j centred on sample
    j * HOP + HOP / 2 (so four steps centre on each video frame)."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("dft", torch.from_numpy(dft_basis()))
        mel = mel_matrix()
        self.register_buffer("mel", torch.from_numpy(np.concatenate([mel, mel], axis=1))[:, :, None])  # re², im²

    @staticmethod
    def padding() -> tuple[int, int]:
        left = (WINDOW - HOP) // 2
        return left, WINDOW - HOP - left

    def forward(self, audio: torch.Tensor) -> torch.Tensor:
        x = F.pad(audio[:, None, :], self.padding())
        spectrum = F.conv1d(x, self.dft, stride=HOP)
        power = F.conv1d(spectrum * spectrum, self.mel)
        return torch.log(power + LOG_FLOOR) * LOG_SCALE


class ChannelNorm(nn.Module):
    """Normalisation over channels at each time step (never across time: docstring above)."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels))

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # [B, C, T]
        centred = x - x.mean(dim=1, keepdim=True)
        scaled = centred / torch.sqrt((centred * centred).mean(dim=1, keepdim=True) + NORM_EPS)
        return scaled * self.weight[None, :, None] + self.bias[None, :, None]


class ShiftedConv(nn.Module):
    """Conv1d whose padding puts `future` of its kernel's reach after the output step and the rest before."""

    def __init__(self, c_in: int, c_out: int, kernel: int, dilation: int = 1, future: int = 0) -> None:
        super().__init__()
        reach = dilation * (kernel - 1)
        self.pads = (reach - future * dilation, future * dilation)
        self.conv = nn.Conv1d(c_in, c_out, kernel, dilation=dilation)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(F.pad(x, self.pads))


class Block(nn.Module):
    """Residual block at 25 fps: x + 1x1(SiLU(dilated(SiLU(norm(x)))))."""

    def __init__(self, channels: int, dilation: int, future: int) -> None:
        super().__init__()
        self.norm = ChannelNorm(channels)
        self.dilated = ShiftedConv(channels, channels, 3, dilation, future)
        self.mix = nn.Conv1d(channels, channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.mix(F.silu(self.dilated(F.silu(self.norm(x)))))


class VoiceNet(nn.Module):
    """audio [B, S] -> ARKit weights [B, T, 52] (unclipped; the ONNX graph clips to 0..1)."""

    def __init__(self, config: VoiceConfig | None = None) -> None:
        super().__init__()
        self.config = config = config or VoiceConfig()
        c = config.channels
        self.front = FrontEnd()
        self.input = nn.Conv1d(N_MELS, c, 2 * STEPS_PER_FRAME, stride=STEPS_PER_FRAME)
        self.blocks = nn.ModuleList(Block(c, d, f) for d, f in config.blocks)
        self.head_norm = ChannelNorm(c)
        self.head_conv = ShiftedConv(c, c, 3, 1, 0)
        self.head = nn.Conv1d(c, config.outputs, 1)
        nn.init.zeros_(self.head.weight)  # start from the rest face
        nn.init.zeros_(self.head.bias)

    def features(self, audio: torch.Tensor) -> torch.Tensor:
        """The fixed front end (no gradient needed): [B, S] -> [B, N_MELS, 4 (SILENCE_BEFORE + T + SILENCE_AFTER)]."""
        silence = (SILENCE_BEFORE * SAMPLES_PER_FRAME, SILENCE_AFTER * SAMPLES_PER_FRAME)
        return self.front(F.pad(fit_length(audio), silence))

    def forward_features(self, mel: torch.Tensor) -> torch.Tensor:
        half = STEPS_PER_FRAME // 2  # frame t reads steps 4t - 2 .. 4t + 5
        x = F.silu(self.input(F.pad(mel, (half, half))))
        for block in self.blocks:
            x = block(x)
        x = self.head(F.silu(self.head_conv(F.silu(self.head_norm(x)))))
        return x.transpose(1, 2)[:, SILENCE_BEFORE:x.shape[2] - SILENCE_AFTER]

    def forward(self, audio: torch.Tensor) -> torch.Tensor:
        return self.forward_features(self.features(audio))


def receptive_field(config: VoiceConfig) -> tuple[float, float]:
    """(seconds before a frame's first sample, seconds after its last) of audio that can change the frame's output:
    the front end's window overhang plus every convolution's reach at its own step size."""
    half = STEPS_PER_FRAME // 2
    steps = [(HOP, half, half)]  # (step in samples, past taps, future taps): the strided input convolution
    steps += [(SAMPLES_PER_FRAME, (2 - f) * d, f * d) for d, f in config.blocks]
    steps.append((SAMPLES_PER_FRAME, 2, 0))  # the causal convolution of the head
    left, right = FrontEnd.padding()  # a frame's first window starts `left` before it, its last ends `right` after
    past = left + sum(size * back for size, back, _ in steps)
    future = right + sum(size * ahead for size, _, ahead in steps)
    return past / SAMPLE_RATE, future / SAMPLE_RATE


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def check_receptive_field(config: VoiceConfig) -> None:
    """ValueError when the network would see past the live session's context or lookahead."""
    past, future = receptive_field(config)
    padded = (SILENCE_BEFORE * SAMPLES_PER_FRAME / SAMPLE_RATE, SILENCE_AFTER * SAMPLES_PER_FRAME / SAMPLE_RATE)
    if past > min(RECEPTIVE_PAST_S, padded[0]) + 1e-9 or future > min(RECEPTIVE_FUTURE_S, padded[1]) + 1e-9:
        raise ValueError(f"receptive field {past:.3f} s before / {future:.3f} s after a frame exceeds "
                         f"{RECEPTIVE_PAST_S} / {RECEPTIVE_FUTURE_S} s")


def translate(model: VoiceNet, audio: np.ndarray) -> np.ndarray:
    """[S] audio -> [frames_for(S), 52] clipped weights (torch; the ONNX graph gives the same)."""
    with torch.no_grad():
        out = model(torch.from_numpy(np.ascontiguousarray(audio, np.float32))[None])[0]
    return out.clamp(0.0, 1.0).numpy()


__all__ = ["FPS", "SAMPLES_PER_FRAME", "SAMPLE_RATE", "VoiceConfig", "VoiceNet", "check_receptive_field",
           "count_parameters", "frames_for", "receptive_field", "translate"]
