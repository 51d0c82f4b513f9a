"""The Motion Translator's streaming form (docs/live.md, "The speaker's own translator"): state in, state out, the
convolutional feature encoder run on each call's new frames and a few refreshed ones, the transformers on the
window's tail with their keys and values kept.

    audio [B, n, 640] (the next n frames of the session's timeline), state [B, S], keep [1] (float32, a whole
    number: how many of the n frames are committed; the rest is provisional, e.g. zeros for lookahead not yet in)
      -> expression [B, n, n_expr], jaw_pose [B, n, 3]: the rows of frames [P - delay, P - delay + n) (P: frames
         committed before the call)
      -> state_out [B, S]: the state after the first `keep` frames (provisional frames never enter it)
      -> delay_frames [1] (int64)

What a call computes is what the windowed graph computes in a live session (context frames of past, the frames,
delay frames of lookahead: one window of context + delay + n frames), except where the windowed graph would
recompute the past:

* The feature encoder (7 strided convolutions, ~75% of a live window's cost) runs on the call's new frames and
  the last `call_refresh` before them (`refresh_frames`, or 0 in the steady form, exported as a second graph on the
  same state: the state keeps what a call of either needs). Each layer keeps the last few inputs its kernel still
  needs (`conv_plan`), at each of the last `refresh_frames` + 1 frame starts;
  a layer that reads past its input's end (the first layer's kernel reads 2 samples into the next feature) makes
  its last outputs from zero padding, as the windowed graph does at a window's end, and recomputes them from real
  inputs in the next call. The layers run time-major ([B, steps, C]), each a MatMul of its taps side by side over
  the whole call (`_conv_time_major`), and the state keeps their parts so.
* The normalisations the windowed graph takes over its whole window (the waveform's mean and variance, then the
  first convolution's per-channel GroupNorm) come from per-frame statistics of the same window kept in the state,
  combined exactly (Chan's pooled variance; the first convolution's from its taps' moments, each frame's mean
  relative to its own waveform mean). They normalise the new and refreshed frames; the kept features of
  older frames keep the normalisation they were made with. That is the one approximation, measured on unseen
  speech in docs/live.md (refreshing as many frames as the delay keeps a frame's features only once the window
  reaches its lookahead, as the windowed call that makes its row sees it).
* The transformers (positional convolution, encoder, decoder) run on the tail of the window only: the call's new
  frames and the `tail_frames` before them (at least every frame whose features the call made again, and the
  delay's frames, whose rows it gives). Their attention still reads the whole window: the keys and values of the
  frames before the tail are kept in the state from the call that last ran them (each layer's, a K/V cache as in a
  decoding transformer; the last decoder layer makes only the rows the call gives). That is the second
  approximation: a frame's hidden states stop changing once it leaves the tail, so they never see more than the
  tail's future, where the windowed graph recomputes them against every frame of each window. `tail_frames=None`
  runs the transformers over the whole window every call instead (the form this replaced; benches compare the two).

`conv_plan` derives each layer's kept inputs from its kernel, stride and padding, so any translator config whose
layers align streams. The module is exported to ONNX beside the windowed graph (exporter/export/translator_graph.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from gaussiantalker.sdk.config import AUDIO_NORM_EPS, FEATURES_PER_FRAME

from .translator import MotionTranslator, PositionalConvEmbedding, TransformerLayer, aligned_padding, conv_kernels

# The live session's defaults (docs/live.md): one second of context, 160 ms of lookahead, at 25 fps.
STREAM_CONTEXT_FRAMES = 25
STREAM_DELAY_FRAMES = 4
# Frames whose features each call makes again from their audio with the newest statistics: as many as the delay,
# so a frame's features are kept only once the window reaches its own lookahead, as the windowed call that makes
# its row sees it (docs/live.md, "The speaker's own translator", has what fewer cost).
STREAM_REFRESH_FRAMES = STREAM_DELAY_FRAMES
# Frames before a call's new ones that the transformers run again (the rest of the window comes from the K/V
# cache): the least the refresh and the delay allow; longer tails cost more and gave no better rows on unseen speech
# (docs/live.md, "The speaker's own translator").
STREAM_TAIL_FRAMES = 5
# The short stream's delay (80 ms at 25 fps), for sessions whose lookahead is shorter than STREAM_DELAY_FRAMES: its
# rows see as much of the future as such a session's windowed call would, with no provisional frames a call. It
# refreshes and runs its tail as the main stream does, so one gate serves both (docs/live.md, "A stream for a short
# lookahead").
STREAM_SHORT_DELAY_FRAMES = 2
# Each stream's delay, in the order of sdk/bundle.py's STREAM_GRAPHS (the main stream first).
STREAM_DELAYS = (STREAM_DELAY_FRAMES, STREAM_SHORT_DELAY_FRAMES)


@dataclass(frozen=True)
class LayerPlan:
    """How one convolution streams: it keeps `keep` inputs, its input lags the frame grid by `lag_in` steps (its
    last `lag_in` inputs are provisional), its outputs by `lag_out`; `right_pad` zeros end its input, as the
    windowed graph's padding does."""

    kernel: int
    stride: int
    keep: int
    lag_in: int
    lag_out: int
    right_pad: int
    rate_in: int  # inputs per video frame


def conv_plan(kernels: tuple[int, ...], strides: tuple[int, ...], samples_per_frame: int) -> tuple[LayerPlan, ...]:
    """Each layer's streaming plan. Output m reads inputs [s*m - p, s*m - p + k); a call that brings inputs up to
    the grid position A + N - lag (exact) must give outputs up to A/s + N/s - lag_out exactly, so
    lag_out = ceil((lag + k - p - s) / s) and the first output needs keep = s * lag_out + p - lag kept inputs.
    Raises ValueError for a layer that cannot stream on the frame grid."""
    plans, lag, rate = [], 0, samples_per_frame
    for kernel, stride in zip(kernels, strides, strict=True):
        pad = aligned_padding(kernel, stride)
        lag_out = max(0, math.ceil((lag + kernel - pad - stride) / stride))
        keep = stride * lag_out + pad - lag
        if keep < 0 or rate % stride:
            raise ValueError(f"a convolution (kernel {kernel}, stride {stride}) does not stream on the frame grid")
        plans.append(LayerPlan(kernel, stride, keep, lag, lag_out, kernel - stride - pad, rate))
        lag, rate = lag_out, rate // stride
    return tuple(plans)


def _pooled(means: torch.Tensor, variances: torch.Tensor, weights: torch.Tensor,
            dim: int = -1) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and variance over axis `dim`'s equal-sized groups, each weighted 1 (counted) or 0 (not: `weights`, one a
    group, shaped to broadcast along `dim`), from each group's own mean and variance (Chan's pooled form: no
    cancellation)."""
    count = weights.sum()
    mean = (means * weights).sum(dim=dim, keepdim=True) / count
    spread = means - mean
    return mean, ((variances + spread * spread) * weights).sum(dim=dim, keepdim=True) / count


def _framed_stats(values: torch.Tensor, frames: int) -> tuple[torch.Tensor, torch.Tensor]:
    """values [B, C, frames * r] -> per-frame mean and variance [B, C, frames]."""
    framed = values.reshape(values.shape[0], values.shape[1], frames, -1)
    mean = framed.mean(dim=-1)
    centred = framed - mean.unsqueeze(-1)
    return mean, (centred * centred).mean(dim=-1)


def _unfold_time_major(x: torch.Tensor, kernel: int, stride: int) -> torch.Tensor:
    """Time-major x [B, L, C_in] -> each output's taps side by side [B, m, kernel * C_in] (tap by tap), the input
    F.conv1d(x, weight, stride=stride) (no padding) reads for each of its m outputs."""
    steps = (x.shape[1] - kernel) // stride + 1
    batch, c_in = x.shape[0], x.shape[2]

    def tap(j: int) -> torch.Tensor:  # input j of every output: [B, m, C_in]
        return x[:, j:j + stride * (steps - 1) + 1:stride]

    if kernel < stride:
        taps = [tap(j) for j in range(kernel)]
    else:
        taps = [x[:, :stride * steps].reshape(batch, steps, stride * c_in)]  # taps 0..stride-1, as they lie
        if kernel == 2 * stride:  # taps stride..2 stride-1: the next output's first ones (L >= stride (m + 1))
            taps.append(x[:, stride:stride * (steps + 1)].reshape(batch, steps, stride * c_in))
        else:
            taps += [tap(j) for j in range(stride, kernel)]
    return torch.cat(taps, dim=-1) if len(taps) > 1 else taps[0]


def _weight_matrix(weight: torch.Tensor) -> torch.Tensor:
    """A Conv1d weight [C_out, C_in, k] as the matrix [k * C_in, C_out] that multiplies `_unfold_time_major`'s
    taps."""
    c_out, c_in, kernel = weight.shape
    return weight.permute(2, 1, 0).reshape(kernel * c_in, c_out)


def _conv_time_major(x: torch.Tensor, weight: torch.Tensor, stride: int) -> torch.Tensor:
    """F.conv1d(x, weight, stride=stride) (no padding, no bias) on time-major x [B, L, C_in] -> [B, m, C_out]: each
    output's taps laid side by side, then one MatMul over every output of the batch, where onnxruntime's Conv makes
    an im2col and a small matrix product per batch item (docs/live.md, "The stream's convolutions time-major")."""
    return _unfold_time_major(x, int(weight.shape[2]), stride) @ _weight_matrix(weight)


def _take(buffer: torch.Tensor, start: torch.Tensor, length: int, dim: int = -1) -> torch.Tensor:
    """buffer[..., start:start + length] along `dim` with a tensor start (a Gather in the graph)."""
    index = start + torch.arange(length, dtype=torch.int64, device=buffer.device)
    return buffer.index_select(dim, index)


# Added to the attention logits of rows made before a stream had audio (its first calls from the all-zero state,
# the rest-state call): exp of it is 0 even in float16, and no logit of layer-normed rows comes near it.
_EMPTY_ROW_LOGIT = -1e4


def _cached_layer(layer: TransformerLayer, x: torch.Tensor, cached_keys: torch.Tensor, cached_values: torch.Tensor,
                  key_bias: torch.Tensor, out_rows: tuple[int, int] | None = None
                  ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
    """One pre-LN transformer layer on the tail rows x [B, T, D], their attention also reading the kept rows'
    keys and values (each [B, H, C, Dh]; key_bias [B, 1, 1, C + T] masks the empty ones). Returns the tail's
    outputs (only rows [first, first + count) of `out_rows`, where the call reads no other: the others' queries,
    attention and feed-forward are not made) and the keys and values of all C + T rows, each [B, H, C + T, Dh]."""
    normed, queries = layer.layer_norm(x), None
    if out_rows is not None:
        first, count = out_rows
        x, queries = x[:, first:first + count], normed[:, first:first + count]
    q, k, v = layer.attention.project(normed, queries)
    keys, values = torch.cat([cached_keys, k], dim=2), torch.cat([cached_values, v], dim=2)
    x = x + layer.attention.attend(q, keys, values, key_bias)
    x = x + layer.feed_forward(layer.final_layer_norm(x))
    return x, (keys, values)


def _positional_tail(embedding: PositionalConvEmbedding, x: torch.Tensor, tail: int) -> torch.Tensor:
    """The positional convolution embedding's last `tail` rows of x [B, L, D]: what embedding(x)[:, L - tail:] is,
    with only those outputs computed. Output t of its 'same' convolution (padding p) reads inputs [t - p, t - p + k),
    zeros past either end, so these read the inputs from L - tail - p on and k - p - 1 zeros after the last. (Its
    grouped convolution as a MatMul a group, taps side by side, took 1.1x the Conv's time in a whole call: more
    nodes and transposes than the Conv saves.)"""
    conv = embedding.conv
    kernel, pad = int(conv.kernel_size[0]), int(conv.padding[0])
    first = x.shape[1] - tail - pad  # the first input read; before the window's start, the padding's zeros
    inputs = x[:, max(first, 0):].transpose(1, 2)
    inputs = F.pad(inputs, (max(-first, 0), kernel - pad - 1))
    rows = F.conv1d(inputs, conv.weight, conv.bias, groups=conv.groups)  # [B, D, tail]
    return x[:, x.shape[1] - tail:] + F.gelu(rows).transpose(1, 2)


class MotionTranslatorStream(nn.Module):
    """A MotionTranslator fed a frame at a time (module docstring); `translator`'s weights, nothing of its own."""

    def __init__(self, translator: MotionTranslator, context_frames: int = STREAM_CONTEXT_FRAMES,
                 delay_frames: int = STREAM_DELAY_FRAMES, refresh_frames: int = STREAM_REFRESH_FRAMES,
                 tail_frames: int | None = STREAM_TAIL_FRAMES, call_refresh: int | None = None) -> None:
        super().__init__()
        cfg = translator.cfg
        self.translator = translator
        self.context_frames, self.delay_frames = int(context_frames), int(delay_frames)
        self.refresh_frames = int(refresh_frames)
        if self.context_frames < 0 or self.delay_frames < 1 or not 0 <= self.refresh_frames <= self.context_frames:
            raise ValueError("a stream needs context_frames >= 0, delay_frames >= 1 and refresh_frames in "
                             "0..context_frames")
        self.samples_per_frame = int(translator.samples_per_frame)
        self.plans = conv_plan(conv_kernels(cfg.conv_strides), tuple(cfg.conv_strides), self.samples_per_frame)
        self.feature_lag = self.plans[-1].lag_out
        self.window_frames = self.context_frames + self.delay_frames  # frames of statistics and features kept
        # features kept as made: those of the window's frames before the refreshed ones
        # frames a call of this module makes again (the state keeps what any of 0..refresh_frames needs, so the
        # graphs of one stream may differ in it: docs/live.md, "The speaker's own translator")
        self.call_refresh = self.refresh_frames if call_refresh is None else int(call_refresh)
        if not 0 <= self.call_refresh <= self.refresh_frames:
            raise ValueError(f"call_refresh must be in 0..{self.refresh_frames}, got {call_refresh}")
        # features kept: the window's up to the committed end (a refreshing call makes its last ones again)
        self.window_features = FEATURES_PER_FRAME * self.window_frames - self.feature_lag
        if FEATURES_PER_FRAME * (self.window_frames - self.refresh_frames) < self.feature_lag:
            raise ValueError("the stream's window is shorter than its feature encoder's lag")
        self.channels, self.dim = cfg.conv_channels, cfg.encoder_dim
        self.tail_frames = self._check_tail(tail_frames)
        pos_left = int(translator.audio_encoder.pos_conv_embed.conv.padding[0])  # features its kernel reads before
        # features kept in the state: the window's, less those before what the tail's positional convolution reads
        self.dropped_features = 0
        if self.tail_frames is not None:
            self.dropped_features = max(0, FEATURES_PER_FRAME * (self.window_frames - self.tail_frames) - pos_left)
        self.kept_features = self.window_features - self.dropped_features
        # frames_seen stops counting where no row of the window is made from the all-zero state's blanks: the
        # window's frames and a stream's first frames, whose positional convolution reads the blank features before
        start_frames = 1 + math.ceil(pos_left / FEATURES_PER_FRAME)
        self.seen_cap = self.window_frames + start_frames
        first = translator.audio_encoder.feature_extractor.conv_layers[0]
        self.conv0_rate = self.samples_per_frame // self.plans[0].stride  # first-layer outputs per frame
        if first.layer_norm is None:
            raise ValueError("the feature encoder's first convolution has no GroupNorm")
        if any(layer.layer_norm is not None for layer in translator.audio_encoder.feature_extractor.conv_layers[1:]):
            raise ValueError("only the feature encoder's first convolution may carry a GroupNorm")
        self.group_norm_eps = float(first.layer_norm.eps)
        self.state_parts = self._state_parts()
        self.state_size = sum(math.prod(shape) for _, shape in self.state_parts)

    def _check_tail(self, tail_frames: int | None) -> int | None:
        """`tail_frames` checked: at least the frames whose features a call makes again and the delay's frames
        (the rows it gives), at most the window."""
        if tail_frames is None:
            return None
        least = max(self.refresh_frames + math.ceil(self.feature_lag / FEATURES_PER_FRAME), self.delay_frames)
        if not least <= int(tail_frames) <= self.window_frames:
            raise ValueError(f"tail_frames must be in {least}..{self.window_frames} (the refreshed frames and the "
                             f"delay's, at most the window), got {tail_frames}")
        return int(tail_frames)

    def _cached_rows(self) -> tuple[int, int]:
        """(encoder rows, decoder rows) whose keys and values the state keeps: the window's before the tail."""
        if self.tail_frames is None:
            return 0, 0
        frames = self.window_frames - self.tail_frames
        return FEATURES_PER_FRAME * frames, frames

    def _state_parts(self) -> list[tuple[str, tuple[int, ...]]]:
        """The flat state's parts in order, each [*shape] per session."""
        w = self.window_frames
        # the feature encoder's parts time-major, as it runs (_conv_time_major)
        parts = [("audio_stats", (2, w)), ("conv0_means", (w, self.channels)), ("conv0_variances", (w, self.channels)),
                 ("refresh_audio", (1, self.refresh_frames * self.samples_per_frame))]
        for i, plan in enumerate(self.plans):  # each layer's kept inputs at the last refresh + 1 frame starts
            parts.append((f"conv{i}", (self.refresh_frames + 1, plan.keep, 1 if i == 0 else self.channels)))
        parts.append(("features", (self.kept_features, self.dim)))
        if self.tail_frames is not None:
            encoder_rows, decoder_rows = self._cached_rows()
            parts.append(("frames_seen", (1,)))  # frames committed since the all-zero state, at most enough
            stacks = (("encoder", self.translator.audio_encoder.encoder, encoder_rows),
                      ("decoder", self.translator.motion_decoder.decoder, decoder_rows))
            for name, stack, rows in stacks:
                for i, layer in enumerate(stack.layers):  # a layer's keys, then its values
                    attention = layer.attention
                    for kind in ("keys", "values"):
                        parts.append((f"{name}{i}_{kind}", (attention.heads, rows, attention.head_dim)))
        return parts

    def _split_state(self, state: torch.Tensor) -> dict[str, torch.Tensor]:
        # Each part as a slice at its offset (a Slice in the graph; torch.split exports as SplitToSequence and one
        # SequenceAt a part, which copy every part whatever reads it)
        parts, offset = {}, 0
        for name, shape in self.state_parts:
            size = math.prod(shape)
            parts[name] = state[:, offset:offset + size].reshape(state.shape[0], *shape)
            offset += size
        return parts

    def forward(self, audio: torch.Tensor, state: torch.Tensor, keep: torch.Tensor):
        batch, frames = audio.shape[0], audio.shape[1]
        kept = self._split_state(state)
        keep_frames = keep.reshape(1).to(torch.int64)
        spf, refresh, most = self.samples_per_frame, self.call_refresh, self.refresh_frames
        new_samples = audio.reshape(batch, 1, frames * spf)
        kept_audio = torch.cat([kept["refresh_audio"], new_samples], dim=-1)  # frames [P - most, P + n)
        new_state = {"refresh_audio": _take(kept_audio, keep_frames * spf, most * spf)}
        samples = kept_audio[..., (most - refresh) * spf:]  # frames [P - refresh, P + n)

        # The waveform's mean and variance over the window (kept frames + new ones).
        audio_mean, audio_var = _framed_stats(new_samples, frames)  # [B, 1, n]
        means = torch.cat([kept["audio_stats"][:, 0:1], audio_mean], dim=-1)
        variances = torch.cat([kept["audio_stats"][:, 1:2], audio_var], dim=-1)
        # Statistics count the kept frames and the committed new ones: provisional zeros would skew them.
        weights = torch.cat([torch.ones(self.window_frames), (torch.arange(frames) < keep_frames).to(audio.dtype)])
        window_mean, window_var = _pooled(means, variances, weights)
        audio_scale = torch.rsqrt(window_var + AUDIO_NORM_EPS)  # [B, 1, 1]
        new_stats = {"audio_stats": torch.cat([means, variances], dim=1)}

        x = samples.reshape(batch, -1, 1)  # time-major from here to the features: [B, L, C]
        for i, (plan, layer) in enumerate(zip(self.plans, self.translator.audio_encoder.feature_extractor.conv_layers,
                                              strict=True)):
            starts = kept[f"conv{i}"]  # [B, most + 1, keep, C]: inputs kept at frames P - most .. P
            buffer = torch.cat([starts[:, most - refresh], x], dim=1)  # inputs from frame P - refresh on
            new_state[f"conv{i}"] = self._frame_starts(buffer, starts[:, :most + 1 - refresh], plan,
                                                       refresh + frames, keep_frames, most + 1)
            if plan.right_pad:
                buffer = F.pad(buffer, (0, 0, 0, plan.right_pad))
            if i == 0:
                y = self._normalised_first(buffer, frames, (means[:, 0], window_mean, audio_scale), weights, kept,
                                           new_stats, layer, plan)
            else:
                y = _conv_time_major(buffer, layer.conv.weight, plan.stride)
            x = F.gelu(y)
        encoder = self.translator.audio_encoder
        features = encoder.feature_projection(encoder.feature_norm(x))  # [B, 2(r + n) + lag, D]
        # the window's features [B, 2 * (W + n), D], less the dropped first ones; the refreshed ones new
        made = kept["features"]
        window = torch.cat([made[:, :made.shape[1] - FEATURES_PER_FRAME * refresh], features], dim=1)
        new_state["features"] = _take(window, keep_frames * FEATURES_PER_FRAME, self.kept_features, dim=1)
        new_state["audio_stats"] = _take(new_stats["audio_stats"], keep_frames, self.window_frames)
        for name in ("conv0_means", "conv0_variances"):
            new_state[name] = _take(new_stats[name], keep_frames, self.window_frames, dim=1)

        if self.tail_frames is None:
            hidden = encoder.encoder(encoder.pos_conv_embed(window))
            hidden = hidden + self.translator.identity.weight[self.translator.speaker_id]
            params = self.translator.motion_decoder(hidden)  # [B, W + n, n_expr + 3]
            rows = params[:, self.context_frames:self.context_frames + frames]
        else:
            rows = self._tail_rows(window, frames, keep_frames, kept, new_state)
        state_out = torch.cat([new_state[name].reshape(batch, -1) for name, _ in self.state_parts], dim=1)
        n_expr = self.translator.n_expr
        delay = torch.full((1,), self.delay_frames, dtype=torch.int64)
        return rows[..., :n_expr], rows[..., n_expr:], state_out, delay

    def _tail_rows(self, window: torch.Tensor, frames: int, keep_frames: torch.Tensor,
                   kept: dict[str, torch.Tensor], new_state: dict[str, torch.Tensor]) -> torch.Tensor:
        """The transformers on the tail of the window [B, L, D] (its last (tail + n) frames' features), reading the
        kept keys and values before it; fills the caches the next call keeps. Returns the call's rows."""
        encoder, decoder = self.translator.audio_encoder, self.translator.motion_decoder
        tail = FEATURES_PER_FRAME * (self.tail_frames + frames)
        # the positional convolution on the tail and the kept features its kernel reads before it; the same zero
        # padding ends the window as in the windowed graph
        hidden = _positional_tail(encoder.pos_conv_embed, window, tail)
        encoder_rows, decoder_rows = self._cached_rows()
        # Attention reads no row of a frame made from the all-zero state's blanks: the frames before the stream's
        # first and its first `start_frames` (whose convolutions and positional convolution read those blanks).
        seen = kept["frames_seen"]  # [B, 1]
        new_state["frames_seen"] = torch.clamp(seen + keep_frames.to(seen.dtype), max=float(self.seen_cap))
        first_clean = self.seen_cap - seen  # the window's first frame made from audio only
        encoder_bias = self._key_bias(first_clean * FEATURES_PER_FRAME, encoder_rows + tail)
        decoder_bias = self._key_bias(first_clean, decoder_rows + tail // FEATURES_PER_FRAME)
        for i, layer in enumerate(encoder.encoder.layers):
            hidden, keys_values = _cached_layer(layer, hidden, kept[f"encoder{i}_keys"], kept[f"encoder{i}_values"],
                                                encoder_bias)
            for kind, part in zip(("keys", "values"), keys_values, strict=True):
                new_state[f"encoder{i}_{kind}"] = _take(part, keep_frames * FEATURES_PER_FRAME, encoder_rows, dim=2)
        hidden = encoder.encoder.layer_norm(hidden) + self.translator.identity.weight[self.translator.speaker_id]
        x = decoder.input_projection(hidden)
        x = x.reshape(x.shape[0], -1, FEATURES_PER_FRAME, x.shape[-1]).mean(dim=2)  # 50 Hz -> 25 fps
        last = len(decoder.decoder.layers) - 1
        out_rows = (self.tail_frames - self.delay_frames, frames)  # the call's rows: the last layer makes only them
        for i, layer in enumerate(decoder.decoder.layers):
            x, keys_values = _cached_layer(layer, x, kept[f"decoder{i}_keys"], kept[f"decoder{i}_values"], decoder_bias,
                                           out_rows if i == last else None)
            for kind, part in zip(("keys", "values"), keys_values, strict=True):
                new_state[f"decoder{i}_{kind}"] = _take(part, keep_frames, decoder_rows, dim=2)
        return decoder.head(decoder.decoder.layer_norm(x))  # [B, n, n_expr + 3]

    @staticmethod
    def _frame_starts(buffer: torch.Tensor, older: torch.Tensor, plan: LayerPlan, frames: int,
                      keep_frames: torch.Tensor, length: int) -> torch.Tensor:
        """A layer's kept inputs at the `length` frame starts up to the committed end after the call: `older`
        [B, m, keep, C] (those up to the call's first frame), then those at each of the `frames` starts after it,
        read from `buffer` [B, L, C] (the layer's inputs from the call's first frame on, its kept ones first)."""
        starts = torch.arange(1, frames + 1, dtype=torch.int64)[:, None] * plan.rate_in
        index = (starts + torch.arange(plan.keep, dtype=torch.int64)[None, :]).reshape(-1)
        made = buffer.index_select(1, index).reshape(buffer.shape[0], frames, plan.keep, buffer.shape[2])
        return _take(torch.cat([older, made], dim=1), keep_frames, length, dim=1)

    @staticmethod
    def _key_bias(first_clean: torch.Tensor, rows: int) -> torch.Tensor:
        """[B, 1, 1, rows] attention-logit bias over a window's rows: _EMPTY_ROW_LOGIT before row `first_clean`
        [B, 1], 0 from it on."""
        index = torch.arange(rows, dtype=first_clean.dtype, device=first_clean.device)
        return ((index < first_clean).to(first_clean.dtype) * _EMPTY_ROW_LOGIT)[:, None, None, :]

    def _normalised_first(self, inputs: torch.Tensor, frames: int,
                          waveform: tuple[torch.Tensor, torch.Tensor, torch.Tensor], weights: torch.Tensor,
                          kept: dict[str, torch.Tensor], new_stats: dict[str, torch.Tensor], layer,
                          plan: LayerPlan) -> torch.Tensor:
        """The first convolution with its GroupNorm over the window, on the raw waveform (inputs [B, L, 1];
        `waveform`: each window frame's mean [B, W + n], the window's mean m [B, 1, 1] and scale a [B, 1, 1]): with
        the waveform normalised as x' = (x - m) * a, GroupNorm(conv(x')) = a * (c - mean) / sqrt(a^2 * var + eps)
        with c = conv(x - m) and c's own per-channel mean and variance over the window. Those come from the taps'
        per-frame mean and covariance (k values an output, not C_out: c's mean is the taps' mean times the weight,
        its variance w^T cov w), and the scale and shift fold into the weight, so no pass over the layer's outputs
        is made for either. Each frame's mean is kept relative to its own waveform mean, so a DC offset cancels
        before any scale (docs/live.md, "The first convolution's statistics from its taps")."""
        frame_means, window_mean, audio_scale = waveform
        refresh = self.call_refresh
        taps = _unfold_time_major(inputs, plan.kernel, plan.stride) - window_mean  # [B, m, k], of x - m
        weight = _weight_matrix(layer.conv.weight)  # [k, C]
        # the new frames' outputs (the refreshed frames' statistics are kept); the last output read padding
        exact = taps[:, refresh * self.conv0_rate:(refresh + frames) * self.conv0_rate]
        framed = exact.reshape(exact.shape[0], frames, self.conv0_rate, exact.shape[2])  # [B, n, r, k]
        tap_mean = framed.mean(dim=2)  # [B, n, k]
        centred = framed - tap_mean.unsqueeze(2)
        tap_cov = centred.transpose(2, 3) @ centred / self.conv0_rate  # [B, n, k, k]
        offsets = (frame_means - window_mean[:, 0]).unsqueeze(-1)  # [B, W + n, 1]: each frame's mean less m
        own_means = (tap_mean - offsets[:, -frames:]) @ weight  # [B, n, C]: conv of the frame's x less its own mean
        # w^T cov w >= 0 exactly; rounding may not keep it so for a channel the taps barely move
        conv_var = torch.clamp(((tap_cov @ weight) * weight).sum(dim=2), min=0.0)
        means = torch.cat([kept["conv0_means"], own_means], dim=1)
        variances = torch.cat([kept["conv0_variances"], conv_var], dim=1)
        new_stats["conv0_means"], new_stats["conv0_variances"] = means, variances
        # each frame's mean of c = conv(x - m): its own, plus its waveform's offset from m times the weight's sums
        mean, var = _pooled(means + offsets * weight.sum(dim=0), variances, weights[:, None], dim=1)  # [B, 1, C]
        # a * (c - mean) / sqrt(a^2 var + eps) * weight + bias: the scale multiplies the weight's columns, the shift
        # rides on a tap of ones
        norm = layer.layer_norm
        scale = audio_scale * torch.rsqrt(audio_scale * audio_scale * var + self.group_norm_eps) * norm.weight
        shift = norm.bias - mean * scale  # [B, 1, C]
        ones = torch.ones_like(taps[..., :1])
        return torch.cat([taps, ones], dim=-1) @ torch.cat([weight * scale, shift], dim=1)
