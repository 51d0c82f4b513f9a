"""The built-in voice's streaming graph, built from its windowed graph: state in, state out, a frame's work per
frame (docs/live.md, "Streaming translators").

The windowed graph (exporter/voice/onnx_graph.py) recomputes its whole receptive field (about 1 s of audio) for every
window. Every layer of the network is a convolution with a bounded reach, so a stream can keep, per layer, the last
inputs its kernel still needs and compute only the new steps:

    audio [B, n, F] (the next n frames of the session's timeline; F = 640), state [B, S], keep [1] (a whole
    number, as float32 since MNN feeds only that: how many of the n frames are real audio to commit; the rest is
    provisional, e.g. zeros standing in for lookahead that has not arrived)
      -> blendshapes [B, n, 52] (or expression [B, n, E] and jaw_pose [B, n, 3]): the rows of frames
         [P - delay, P - delay + n) where P is the frames committed before this call
      -> state_out [B, S]: every layer's kept inputs after the first `keep` frames, so provisional frames never
         enter the state
      -> delay_frames [1] (int64): how many frames a row lags the audio it is fed (4 = 160 ms: the network's reach
         into the future, rounded up to frames)

Per layer (in the order of the flat state): the front end keeps 280 samples (its 25 ms windows step 10 ms; a frame's
four steps need the 120 samples before it and 160 of the previous frame, so the step grid stays the windowed
graph's), the strided input convolution 5 log-mel steps, each residual block its dilated convolution's 2 x dilation
inputs and, for a block that looks ahead, its residual path delayed by those future frames, and the head's causal
convolution 2 frames. The per-step channel norm needs no state.

Everything is read from the windowed graph itself (its weights, each convolution's dilation and padding, the front
end's constants), so a bundle exported from a checkpoint whose voice was attached long ago streams too, and the
exporter needs nothing of the voice's training code. A stream fed from the rest state (the state after a second of
silence, which is what the windowed graph sees before a session's first audio) gives the windowed graph's rows to
float rounding: `tests/test_voice_stream.py` checks it on unseen speech.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from .onnx_build import OPSET, VOICE_PRODUCER, Graph, channel_norm, silu

STREAM_PRODUCER = VOICE_PRODUCER + " stream"


@dataclass(frozen=True)
class StatePart:
    """One layer's kept inputs in the flat state: `length` steps of `channels` (stored steps first, channels last,
    as the graph lays them), `per_frame` of them per video frame."""

    name: str
    channels: int
    length: int
    per_frame: int

    @property
    def size(self) -> int:
        return self.channels * self.length


@dataclass(frozen=True)
class VoiceLayout:
    """What the streaming graph needs to know of a windowed voice graph: its weights by module name, the residual
    blocks as (dilation, future taps), and the front end's constants."""

    weights: dict
    blocks: tuple[tuple[int, int], ...]
    hop: int  # front-end step (samples)
    window: int  # front-end window (samples)
    frame_samples: int
    steps_per_frame: int
    log_floor: float
    log_scale: float
    norm_eps: float
    outputs: tuple[str, ...]  # the windowed graph's outputs, in order

    @property
    def channels(self) -> int:
        return int(self.weights["input.weight"].shape[0])

    @property
    def mels(self) -> int:
        return int(self.weights["input.weight"].shape[1])

    def state_parts(self) -> list[StatePart]:
        """The flat state's layout: the front end keeps the 120 samples before a frame's first step plus the
        previous frame's last step (not computed until this frame's audio is in); the strided input convolution
        (8 steps, stride 4) the steps from two before the next frame on, three of the previous frame's not yet read."""
        c, step = self.channels, self.steps_per_frame
        parts = [StatePart("front", 1, (self.window - self.hop) // 2 + self.hop, self.frame_samples),
                 StatePart("input", self.mels, 2 * step - step + 1, step)]
        for k, (dilation, future) in enumerate(self.blocks):
            parts.append(StatePart(f"blocks.{k}.dilated", c, 2 * dilation, 1))
            if future:
                parts.append(StatePart(f"blocks.{k}.residual", c, future * dilation, 1))
        parts.append(StatePart("head_conv", c, 2, 1))
        return parts

    @property
    def delay_frames(self) -> int:
        """Frames a row lags the audio fed: one for the input convolution's reach, plus each block's future taps."""
        return 1 + sum(dilation * future for dilation, future in self.blocks)


def _base_name(name: str) -> str:
    """An initializer's module name: the voice's graph builder suffixes each with `_<count>`."""
    return re.sub(r"_\d+$", "", name)


def is_voice_graph(model: onnx.ModelProto) -> bool:
    """Whether `model` is the built-in voice's windowed graph (written by exporter/voice/onnx_graph.py)."""
    return model.producer_name == VOICE_PRODUCER and any(i.name.startswith("blocks.0.dilated.conv.weight")
                                                         for i in model.graph.initializer)


def voice_layout(model: onnx.ModelProto) -> VoiceLayout:
    """The layout of a built-in voice's windowed graph (ValueError for any other graph)."""
    if not is_voice_graph(model):
        raise ValueError("not the built-in voice's windowed graph")
    weights = {_base_name(i.name): numpy_helper.to_array(i) for i in model.graph.initializer}
    convs = {_base_name(n.input[1]): {a.name: helper.get_attribute_value(a) for a in n.attribute}
             for n in model.graph.node if n.op_type == "Conv" and len(n.input) > 1}
    blocks = []
    while f"blocks.{len(blocks)}.dilated.conv.weight" in weights:
        attrs = convs[f"blocks.{len(blocks)}.dilated.conv.weight"]
        dilation = int(attrs.get("dilations", [1])[0])
        blocks.append((dilation, int(attrs.get("pads", [0, 0])[1]) // dilation))
    scalar = lambda name: float(np.asarray(weights[name]).reshape(-1)[0])  # noqa: E731
    return VoiceLayout(weights, tuple(blocks), hop=int(convs["front.dft"]["strides"][0]),
                       window=int(weights["front.dft"].shape[-1]), frame_samples=int(scalar("samples_per_frame")),
                       steps_per_frame=int(convs["input.weight"]["strides"][0]), log_floor=scalar("floor"),
                       log_scale=scalar("log_scale"), norm_eps=scalar("eps"),
                       outputs=tuple(o.name for o in model.graph.output))


class _Stream:
    """Builds the streaming nodes, channels last ([B, steps, C]): each layer's kept inputs are cut from `state`,
    joined before the new steps, and the kept inputs after the committed frames go to the outputs."""

    def __init__(self, g: Graph, layout: VoiceLayout) -> None:
        self.g, self.parts = g, {p.name: p for p in layout.state_parts()}
        self.offsets, offset = {}, 0
        for part in layout.state_parts():
            self.offsets[part.name] = offset
            offset += part.size
        self.size = offset
        self.kept: list[str] = []
        i64 = np.int64
        self.one_axis = g.const("axis1", np.array([1], i64))
        self.keep = g.op("Cast", ["keep"], "keep_frames", to=TensorProto.INT64)

    def join(self, name: str, x: str) -> str:
        """State part `name` [B, L, C] joined before `x` [B, m, C] (or [B, L] before [B, m] for the samples):
        [B, L + m, C]; records the part's new value."""
        g, part, i64 = self.g, self.parts[name], np.int64
        start = self.offsets[name]
        flat = g.op("Slice", ["state", g.const("start", np.array([start], i64)),
                              g.const("stop", np.array([start + part.size], i64)), self.one_axis], f"{name}.flat")
        shape = [-1, part.length] if part.channels == 1 else [-1, part.length, part.channels]
        kept = g.op("Reshape", [flat, g.const("shape", np.array(shape, i64))], f"{name}.kept")
        joined = g.op("Concat", [kept, x], f"{name}.joined", axis=1)
        first = g.op("Mul", [self.keep, g.const("per_frame", np.array([part.per_frame], i64))], f"{name}.first")
        new = g.op("Slice", [joined, first, g.op("Add", [first, g.const("length", np.array([part.length], i64))]),
                             self.one_axis], f"{name}.new")
        self.kept.append(g.op("Flatten", [new], f"{name}.out", axis=1))
        return joined

    def steps(self, x: str, first: int, last: int) -> str:
        """x[:, first:len - last] on the steps axis (a convolution tap's view of its joined input)."""
        g, i64 = self.g, np.int64
        stop = -last if last else np.iinfo(i64).max
        return g.op("Slice", [x, g.const("start", np.array([first], i64)), g.const("stop", np.array([stop], i64)),
                              self.one_axis], "tap")


def _taps_matmul(g: Graph, columns: str, weight: np.ndarray, bias: np.ndarray | None, prefix: str,
                 width: int | None = None) -> str:
    """A convolution as one matrix product over every session's steps: `columns` [B, m, k C] (the k taps' inputs
    side by side) times the kernel laid out [k C, C_out]. onnxruntime's Conv runs a small GEMM per batch item, which
    reads the whole kernel again for each session of a call; one MatMul reads it once (docs/live.md, "Streaming
    translators"). The kernel is the windowed graph's weight [C_out, C, k] (zero-padded to `width` taps), laid out
    by nodes on that initializer, which onnxruntime folds once when it loads the graph: the bundle stores it once."""
    kernel = g.const(f"{prefix}.weight", weight)
    if width is not None and width > weight.shape[2]:
        pads = np.array([0, 0, 0, 0, 0, width - weight.shape[2]], np.int64)
        kernel = g.op("Pad", [kernel, g.const("pads", pads)], f"{prefix}.padded")
    laid = g.op("Reshape", [g.op("Transpose", [kernel], f"{prefix}.taps_first", perm=[2, 1, 0]),
                            g.const("shape", np.array([-1, weight.shape[0]], np.int64))], f"{prefix}.kernel")
    out = g.op("MatMul", [columns, laid], f"{prefix}.product")
    return out if bias is None else g.op("Add", [out, g.const(f"{prefix}.bias", bias)], prefix)


def _dilated(g: Graph, s: _Stream, joined: str, w: dict, prefix: str, dilation: int) -> str:
    """A 3-tap convolution of `dilation` over `joined` [B, 2 dilation + m, C] -> [B, m, C_out]."""
    taps = [s.steps(joined, t * dilation, (2 - t) * dilation) for t in range(3)]
    return _taps_matmul(g, g.op("Concat", taps, "columns", axis=2), w[f"{prefix}.weight"], w[f"{prefix}.bias"],
                        prefix)


def _pointwise(g: Graph, x: str, w: dict, prefix: str) -> str:
    """A 1-tap convolution over `x` [B, m, C]."""
    return _taps_matmul(g, x, w[f"{prefix}.weight"], w[f"{prefix}.bias"], prefix)


def _stream_network(g: Graph, layout: VoiceLayout) -> tuple[str, int]:
    """Nodes from `audio` [B, n, F], `state`, `keep` to the clipped ARKit weights [B, n, 52]; returns that value's
    name and the flat state's size. Every convolution is a matrix product over its taps (`_taps_matmul`)."""
    w, s, i64 = layout.weights, _Stream(g, layout), np.int64
    hop, window, step = layout.hop, layout.window, layout.steps_per_frame
    samples = g.op("Reshape", ["audio", g.const("shape", np.array([0, -1], i64))], "samples")  # [B, n F]
    signal = s.join("front", samples)  # [B, L + n F]: window w reads [w hop, w hop + window)
    # Cut into hops, padded with zeros to whole hops past the last window: window w is hops w .. w + span - 1.
    span = -(-window // hop)
    pad = (span - 1) * hop - s.parts["front"].length
    if pad < 0 or layout.frame_samples != step * hop or int(w["input.weight"].shape[2]) != 2 * step:
        raise ValueError("the voice graph's front end or input convolution is not the shape its stream is built for")
    hops = g.op("Reshape", [g.op("Pad", [signal, g.const("pads", np.array([0, 0, 0, pad], i64))], "padded"),
                            g.const("shape", np.array([0, -1, hop], i64))], "hops")
    taps = [s.steps(hops, t, span - 1 - t) for t in range(span)]
    spectrum = _taps_matmul(g, g.op("Concat", taps, "frames", axis=2), w["front.dft"], None, "front.dft",
                            width=span * hop)
    mel = _taps_matmul(g, g.op("Mul", [spectrum, spectrum]), w["front.mel"], None, "front.mel")
    logmel = g.op("Mul", [g.op("Log", [g.op("Add", [mel, g.const("floor", np.float32(layout.log_floor))])]),
                          g.const("log_scale", np.float32(layout.log_scale))], "logmel")  # [B, step n, mels]
    # The strided input convolution: 2 step-long taps of whole frames' steps, the joined input's last step unread.
    joined = s.steps(s.join("input", logmel), 0, 1)  # [B, step (n + 1), mels]
    chunks = g.op("Reshape", [joined, g.const("shape", np.array([0, -1, step * layout.mels], i64))], "chunks")
    columns = g.op("Concat", [s.steps(chunks, 0, 1), s.steps(chunks, 1, 0)], "columns", axis=2)
    x = silu(g, _taps_matmul(g, columns, w["input.weight"], w["input.bias"], "input"))
    for k, (dilation, future) in enumerate(layout.blocks):
        p = f"blocks.{k}"
        h = silu(g, channel_norm(g, x, w, f"{p}.norm", layout.norm_eps, axis=-1))
        h = silu(g, _dilated(g, s, s.join(f"{p}.dilated", h), w, f"{p}.dilated.conv", dilation))
        if future:  # a block that looks ahead: its residual path waits as long
            joined = s.join(f"{p}.residual", x)
            x = g.op("Slice", [joined, g.const("zero", np.array([0], i64)), g.op("Shape", [h], start=1, end=2),
                               s.one_axis], f"{p}.delayed")
        x = g.op("Add", [x, _pointwise(g, h, w, f"{p}.mix")], f"{p}.out")
    h = silu(g, channel_norm(g, x, w, "head_norm", layout.norm_eps, axis=-1))
    h = silu(g, _dilated(g, s, s.join("head_conv", h), w, "head_conv.conv", 1))
    out = _pointwise(g, h, w, "head")
    g.op("Concat", s.kept, output="state_out", axis=1)
    return g.op("Clip", [out, g.const("lo", np.float32(0.0)), g.const("hi", np.float32(1.0))], "weights"), s.size


def stream_model_of(model: onnx.ModelProto) -> onnx.ModelProto | None:
    """The streaming graph of a built-in voice's windowed graph (ARKit or FLAME head, with the maps it holds now);
    None for any other audio model (a user's own: its layers are unknown, so it is only run windowed)."""
    if not is_voice_graph(model):
        return None
    layout = voice_layout(model)
    g = Graph()
    weights, size = _stream_network(g, layout)
    if "expression_map" in layout.weights:
        expression_map, jaw_map = layout.weights["expression_map"], layout.weights["jaw_map"]
        g.op("MatMul", [weights, g.const("expression_map", expression_map.astype(np.float32))], output="expression")
        g.op("MatMul", [weights, g.const("jaw_map", jaw_map.astype(np.float32))], output="jaw_pose")
        outputs = [("expression", int(expression_map.shape[1])), ("jaw_pose", 3)]
    else:
        g.op("Identity", [weights], output="blendshapes")
        outputs = [("blendshapes", int(layout.weights["head.weight"].shape[0]))]
    g.nodes.append(helper.make_node("Constant", [], ["delay_frames"], name="delay_frames",
                                    value=numpy_helper.from_array(np.array([layout.delay_frames], np.int64))))
    inputs = [helper.make_tensor_value_info("audio", TensorProto.FLOAT, ["batch", "frames", layout.frame_samples]),
              helper.make_tensor_value_info("state", TensorProto.FLOAT, ["batch", size]),
              helper.make_tensor_value_info("keep", TensorProto.FLOAT, [1])]
    out = [helper.make_tensor_value_info(name, TensorProto.FLOAT, ["batch", "frames", width])
           for name, width in outputs]
    out += [helper.make_tensor_value_info("state_out", TensorProto.FLOAT, ["batch", size]),
            helper.make_tensor_value_info("delay_frames", TensorProto.INT64, [1])]
    stream = helper.make_model(helper.make_graph(g.nodes, "voice_stream", inputs, out, g.initializers),
                               opset_imports=[helper.make_opsetid("", OPSET)], producer_name=STREAM_PRODUCER,
                               doc_string=model.doc_string)
    stream.ir_version = 8  # opset 17's IR version, as the windowed graph's
    onnx.checker.check_model(stream, full_check=True)
    return stream


__all__ = ["STREAM_PRODUCER", "StatePart", "VoiceLayout", "is_voice_graph", "stream_model_of", "voice_layout"]
