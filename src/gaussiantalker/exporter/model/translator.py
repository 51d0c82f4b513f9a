"""Speaker-specific Motion Translator (paper §3.2): audio 16 kHz -> FLAME expression and jaw pose per video frame.

    audio [B, S] ──► per-utterance normalisation (zero mean, unit variance; in the graph)
                 ──► universal audio encoder (wav2vec 2.0-style): 7-layer conv feature encoder (320 samples per
                     50 Hz feature), LayerNorm + projection, convolutional relative positional embedding,
                     pre-LN transformer encoder
                 ──► + identity embedding row of this speaker (E_id(p), fixed per exported speaker)
                 ──► customized motion decoder (non-autoregressive): projection, 50 Hz -> 25 fps by averaging
                     feature pairs, pre-LN transformer, linear head
                 ──► expression [B, T, n_expr], jaw_pose [B, T, 3] (axis-angle), T = S / 640

Length contract: S must be a multiple of samples_per_frame (640 = 320 samples per feature x FEATURES_PER_FRAME);
the runtime zero-pads audio to that. The convolution paddings are chosen so that such an input gives exactly
S / 320 features (wav2vec 2.0 itself has no padding and drops a partial feature), so frames and features align.
`translate` checks the contract with a clear ValueError; the traced graph itself does not check.

Only common ONNX ops are used (Conv, MatMul, Softmax, LayerNormalization, InstanceNormalization, Gelu, Reshape,
Transpose, ReduceMean, Slice, ...; no fused attention), so the graph also suits MNN.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from gaussiantalker.sdk.audio import MAX_SAMPLE_MAGNITUDE
from gaussiantalker.sdk.config import AUDIO_NORM_EPS, FEATURES_PER_FRAME, TranslatorConfig

# wav2vec 2.0 conv kernel per stride for its standard stride pattern; other patterns use kernel = 2 * stride.
_WAV2VEC2_STRIDES = (5, 2, 2, 2, 2, 2, 2)
_WAV2VEC2_KERNELS = (10, 3, 3, 3, 3, 2, 2)


def paper_translator_config() -> TranslatorConfig:
    """wav2vec 2.0 LARGE-class encoder (the paper's XLSR-53-based ASR encoder size) with a mid-size decoder."""
    return TranslatorConfig(
        conv_channels=512,
        conv_strides=_WAV2VEC2_STRIDES,
        encoder_dim=1024,
        encoder_layers=24,
        encoder_heads=16,
        encoder_ffn=4096,
        pos_conv_kernel=128,
        pos_conv_groups=16,
        decoder_dim=256,
        decoder_layers=4,
        decoder_heads=4,
        decoder_ffn=1024,
        n_speakers=16,
    )


def conv_kernels(strides: tuple[int, ...]) -> tuple[int, ...]:
    """Kernel size per conv layer: wav2vec 2.0's for its stride pattern, else 2 * stride."""
    if tuple(strides) == _WAV2VEC2_STRIDES:
        return _WAV2VEC2_KERNELS
    return tuple(2 * s for s in strides)


def aligned_padding(kernel: int, stride: int) -> int:
    """Padding p so that a conv maps an input of length stride * m to exactly m outputs.

    out = floor((stride*m + 2p - kernel) / stride) + 1 = m  <=>  -stride <= 2p - kernel <= -1.
    """
    p = max(0, math.ceil((kernel - stride) / 2))
    if not -stride <= 2 * p - kernel <= -1:
        raise ValueError(f"no padding aligns kernel {kernel} with stride {stride}")
    return p


def check_audio_length(n_samples: int, spf: int) -> int:
    """Return the number of video frames for n_samples, or raise ValueError unless it is a positive multiple of spf."""
    if n_samples <= 0 or n_samples % spf != 0:
        raise ValueError(
            f"translator audio length must be a positive multiple of {spf} samples (one video frame), "
            f"got {n_samples}; zero-pad the clip to the next multiple first"
        )
    return n_samples // spf


def normalize_waveform(audio: torch.Tensor) -> torch.Tensor:
    """Per-utterance zero-mean unit-variance normalisation over time ([B, S]); silence stays exactly 0."""
    centred = audio - audio.mean(dim=-1, keepdim=True)
    var = (centred * centred).mean(dim=-1, keepdim=True)
    return centred * torch.rsqrt(var + AUDIO_NORM_EPS)


class ConvLayer(nn.Module):
    """One feature-encoder layer: Conv1d (no bias, as wav2vec 2.0-base) [+ per-channel GroupNorm] + GELU."""

    def __init__(self, c_in: int, c_out: int, kernel: int, stride: int, group_norm: bool) -> None:
        super().__init__()
        self.conv = nn.Conv1d(c_in, c_out, kernel, stride, padding=aligned_padding(kernel, stride), bias=False)
        self.layer_norm = nn.GroupNorm(c_out, c_out) if group_norm else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # [B, C_in, L] -> [B, C_out, L / stride]
        x = self.conv(x)
        if self.layer_norm is not None:
            x = self.layer_norm(x)
        return F.gelu(x)


class FeatureEncoder(nn.Module):
    """wav2vec 2.0 convolutional feature encoder: raw audio [B, S] -> features [B, S / 320, C]."""

    def __init__(self, cfg: TranslatorConfig) -> None:
        super().__init__()
        kernels, c = conv_kernels(cfg.conv_strides), cfg.conv_channels
        self.conv_layers = nn.ModuleList(
            ConvLayer(1 if i == 0 else c, c, k, s, group_norm=i == 0)
            for i, (k, s) in enumerate(zip(kernels, cfg.conv_strides, strict=True))
        )

    def forward(self, audio: torch.Tensor) -> torch.Tensor:
        x = audio.unsqueeze(1)  # [B, 1, S]
        for layer in self.conv_layers:
            x = layer(x)
        return x.transpose(1, 2)  # [B, F, C]


class PositionalConvEmbedding(nn.Module):
    """wav2vec 2.0 relative positional embedding: grouped conv over time, 'same' length, GELU, added to x."""

    def __init__(self, dim: int, kernel: int, groups: int) -> None:
        super().__init__()
        self.conv = nn.Conv1d(dim, dim, kernel, padding=kernel // 2, groups=groups)
        self.drop_last = kernel % 2 == 0  # an even kernel with padding k/2 yields one extra frame

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # [B, F, D] -> [B, F, D]
        y = self.conv(x.transpose(1, 2))
        if self.drop_last:
            y = y[:, :, :-1]
        return x + F.gelu(y).transpose(1, 2)


class SelfAttention(nn.Module):
    """Multi-head self-attention written with plain MatMul/Softmax (portable to any ONNX backend)."""

    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        self.heads, self.head_dim = heads, dim // heads
        self.q_proj, self.k_proj = nn.Linear(dim, dim), nn.Linear(dim, dim)
        self.v_proj, self.out_proj = nn.Linear(dim, dim), nn.Linear(dim, dim)

    def _split(self, x: torch.Tensor) -> torch.Tensor:  # [B, T, D] -> [B, H, T, Dh]
        return x.reshape(x.shape[0], -1, self.heads, self.head_dim).transpose(1, 2)

    def project(self, x: torch.Tensor, query_rows: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Scaled queries, keys and values [B, H, T, Dh] of the rows x [B, T, D]; the queries of `query_rows` [B, Tq,
        D] instead where given (rows of x whose outputs alone are read)."""
        q = self._split(self.q_proj(x if query_rows is None else query_rows) * (self.head_dim**-0.5))
        return q, self._split(self.k_proj(x)), self._split(self.v_proj(x))

    def attend(self, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor,
               key_bias: torch.Tensor | None = None) -> torch.Tensor:
        """Queries [B, H, Tq, Dh] over keys and values [B, H, Tk, Dh] -> [B, Tq, D] (a streaming call's new rows
        read the keys and values kept from earlier calls too; `key_bias` [B, 1, 1, Tk], added to the logits, masks
        kept rows that hold no frame yet)."""
        logits = q @ k.transpose(-1, -2)  # [B, H, Tq, Tk]
        attn = torch.softmax(logits if key_bias is None else logits + key_bias, dim=-1)
        y = (attn @ v).transpose(1, 2)  # [B, Tq, H, Dh]
        return self.out_proj(y.reshape(y.shape[0], -1, self.heads * self.head_dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.attend(*self.project(x))


class FeedForward(nn.Module):
    """Transformer position-wise feed-forward: Linear -> GELU -> Linear."""

    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        self.intermediate_dense, self.output_dense = nn.Linear(dim, hidden), nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.output_dense(F.gelu(self.intermediate_dense(x)))


class TransformerLayer(nn.Module):
    """Pre-LN transformer layer (as wav2vec 2.0-large): x + Attn(LN(x)), then x + FFN(LN(x))."""

    def __init__(self, dim: int, heads: int, ffn: int) -> None:
        super().__init__()
        self.layer_norm, self.attention = nn.LayerNorm(dim), SelfAttention(dim, heads)
        self.final_layer_norm, self.feed_forward = nn.LayerNorm(dim), FeedForward(dim, ffn)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.attention(self.layer_norm(x))
        return x + self.feed_forward(self.final_layer_norm(x))


class TransformerStack(nn.Module):
    """A stack of pre-LN transformer layers followed by a final LayerNorm."""

    def __init__(self, dim: int, layers: int, heads: int, ffn: int) -> None:
        super().__init__()
        self.layers = nn.ModuleList(TransformerLayer(dim, heads, ffn) for _ in range(layers))
        self.layer_norm = nn.LayerNorm(dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for layer in self.layers:
            x = layer(x)
        return self.layer_norm(x)


class UniversalAudioEncoder(nn.Module):
    """wav2vec 2.0-style encoder E_uni: normalised audio [B, S] -> content features [B, S / 320, encoder_dim]."""

    def __init__(self, cfg: TranslatorConfig) -> None:
        super().__init__()
        self.feature_extractor = FeatureEncoder(cfg)
        self.feature_norm = nn.LayerNorm(cfg.conv_channels)
        self.feature_projection = nn.Linear(cfg.conv_channels, cfg.encoder_dim)
        self.pos_conv_embed = PositionalConvEmbedding(cfg.encoder_dim, cfg.pos_conv_kernel, cfg.pos_conv_groups)
        self.encoder = TransformerStack(cfg.encoder_dim, cfg.encoder_layers, cfg.encoder_heads, cfg.encoder_ffn)

    def forward(self, audio: torch.Tensor) -> torch.Tensor:
        x = self.feature_projection(self.feature_norm(self.feature_extractor(audio)))
        return self.encoder(self.pos_conv_embed(x))


class MotionDecoder(nn.Module):
    """Customized motion decoder D_m: 50 Hz features [B, 2T, D] -> per-frame FLAME params [B, T, n_expr + 3]."""

    def __init__(self, cfg: TranslatorConfig, n_out: int) -> None:
        super().__init__()
        self.input_projection = nn.Linear(cfg.encoder_dim, cfg.decoder_dim)
        self.decoder = TransformerStack(cfg.decoder_dim, cfg.decoder_layers, cfg.decoder_heads, cfg.decoder_ffn)
        self.head = nn.Linear(cfg.decoder_dim, n_out)
        nn.init.zeros_(self.head.weight)  # start from the neutral face (all parameters 0)
        nn.init.zeros_(self.head.bias)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        x = self.input_projection(features)
        x = x.reshape(x.shape[0], -1, FEATURES_PER_FRAME, x.shape[-1]).mean(dim=2)  # 50 Hz -> 25 fps
        return self.head(self.decoder(x))


def _check_config(cfg: TranslatorConfig, n_expr: int, speaker_id: int) -> None:
    """Raise ValueError for a translator config whose sizes cannot fit together."""
    problems = []
    if cfg.encoder_dim % cfg.encoder_heads or cfg.decoder_dim % cfg.decoder_heads:
        problems.append("encoder_dim/decoder_dim must be divisible by their head counts")
    if cfg.encoder_dim % cfg.pos_conv_groups:
        problems.append("encoder_dim must be divisible by pos_conv_groups")
    if len(cfg.conv_strides) < 1 or min(cfg.conv_strides) < 1:
        problems.append("conv_strides must be a non-empty tuple of positive ints")
    if n_expr < 1:
        problems.append(f"n_expr must be positive, got {n_expr}")
    if not 0 <= speaker_id < cfg.n_speakers:
        problems.append(f"speaker_id {speaker_id} outside [0, {cfg.n_speakers})")
    if problems:
        raise ValueError("invalid translator config: " + "; ".join(problems))


class MotionTranslator(nn.Module):
    """Speaker-specific Motion Translator: audio [B, S] -> (expression [B, T, n_expr], jaw_pose [B, T, 3]).

    S must be a multiple of `samples_per_frame` (640); T = S / 640. The speaker id is fixed at construction
    (a plain int, not a graph input or a state-dict entry): E_id(p) is one row of `identity`.
    """

    def __init__(self, cfg: TranslatorConfig, n_expr: int, speaker_id: int = 0) -> None:
        super().__init__()
        _check_config(cfg, n_expr, speaker_id)
        self.cfg, self.n_expr, self.speaker_id = cfg, int(n_expr), int(speaker_id)
        self.samples_per_frame = cfg.samples_per_frame
        self.audio_encoder = UniversalAudioEncoder(cfg)
        self.identity = nn.Embedding(cfg.n_speakers, cfg.encoder_dim)
        self.motion_decoder = MotionDecoder(cfg, n_expr + 3)

    def forward(self, audio: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        features = self.audio_encoder(normalize_waveform(audio))  # [B, 2T, D]
        features = features + self.identity.weight[self.speaker_id]
        params = self.motion_decoder(features)  # [B, T, n_expr + 3]
        return params[..., : self.n_expr], params[..., self.n_expr :]


def count_parameters(model: nn.Module) -> int:
    """Number of scalar parameters in a module."""
    return sum(p.numel() for p in model.parameters())


def translate(model: MotionTranslator, audio: np.ndarray | torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Run the translator on [S] or [B, S] audio after checking S % 640 == 0; returns numpy (expression, jaw_pose).

    A 1-D input gives [T, n_expr] and [T, 3]; a 2-D input keeps its batch axis.
    """
    x = torch.as_tensor(np.asarray(audio, dtype=np.float32))
    if x.ndim not in (1, 2):
        raise ValueError(f"audio must be [samples] or [batch, samples], got shape {tuple(x.shape)}")
    check_audio_length(int(x.shape[-1]), model.samples_per_frame)
    if not torch.isfinite(x).all():
        raise ValueError("audio contains NaN or Inf samples")
    if x.numel() and float(x.abs().max()) > MAX_SAMPLE_MAGNITUDE:  # the normalisation's variance would overflow
        raise ValueError(f"audio samples exceed ±{MAX_SAMPLE_MAGNITUDE:.0f} (full scale is ±1)")
    with torch.no_grad():
        expression, jaw_pose = model(x.reshape(-1, x.shape[-1]))
    if x.ndim == 1:
        expression, jaw_pose = expression[0], jaw_pose[0]
    return expression.numpy(), jaw_pose.numpy()
