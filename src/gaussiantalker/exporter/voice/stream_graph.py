"""The voice network's streaming graph: state in, state out, a frame's work per frame (docs/live.md, "Streaming
translators").

The windowed graph (onnx_graph.py) recomputes its whole receptive field (about 1 s of audio) for every window. Every
layer of the network is a convolution with a bounded reach, so a stream can keep, per layer, the last inputs its
kernel still needs and compute only the new steps:

    audio [B, n, 640] (the next n frames of the session's timeline), state [B, S], keep [1] (int64: how many of
    the n frames are real audio to commit; the rest is provisional, e.g. zeros standing in for lookahead that has
    not arrived)
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
convolution 2 frames. The per-step channel norm needs no state. A stream fed from the rest state (the state after a
second of silence, which is what the windowed graph sees before a session's first audio) gives the windowed graph's
rows to float rounding: `tests/test_voice_stream.py` checks it on unseen speech.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
import onnx
import torch
from onnx import TensorProto, helper, numpy_helper

from .model import HOP, LOG_FLOOR, LOG_SCALE, N_MELS, SAMPLES_PER_FRAME, STEPS_PER_FRAME, WINDOW, VoiceConfig, VoiceNet
from .onnx_graph import OPSET, PRODUCER, _conv, _Graph, _norm, _silu, _weights

STREAM_PRODUCER = PRODUCER + " stream"
# Front-end samples kept between calls: a frame's first step starts (WINDOW - HOP) / 2 = 120 samples before it and
# the step before that one (the previous frame's last, not computed until this frame's audio is in) 160 earlier.
FRONT_STATE = (WINDOW - HOP) // 2 + HOP
# Log-mel steps kept for the strided input convolution (kernel 8 steps, stride 4): the frame whose steps come next
# reads from two steps before it, and three of the previous frame's steps were not yet readable.
INPUT_STATE = 2 * STEPS_PER_FRAME - STEPS_PER_FRAME + 1


@dataclass(frozen=True)
class StatePart:
    """One layer's kept inputs in the flat state: `channels` x `length`, `per_frame` of them per video frame."""

    name: str
    channels: int
    length: int
    per_frame: int

    @property
    def size(self) -> int:
        return self.channels * self.length


def state_parts(config: VoiceConfig) -> list[StatePart]:
    """The flat state's layout for a network of `config`."""
    c = config.channels
    parts = [StatePart("front", 1, FRONT_STATE, SAMPLES_PER_FRAME), StatePart("input", N_MELS, INPUT_STATE,
                                                                             STEPS_PER_FRAME)]
    for k, (dilation, future) in enumerate(config.blocks):
        parts.append(StatePart(f"blocks.{k}.dilated", c, 2 * dilation, 1))
        if future:
            parts.append(StatePart(f"blocks.{k}.residual", c, future * dilation, 1))
    parts.append(StatePart("head_conv", c, 2, 1))
    return parts


def delay_frames(config: VoiceConfig) -> int:
    """Frames a row lags the audio fed: one for the input convolution's reach, plus each block's future taps."""
    return 1 + sum(dilation * future for dilation, future in config.blocks)


class _Stream:
    """Builds the streaming nodes: each layer's kept inputs are cut from `state`, joined before the new steps,
    and the kept inputs after the committed frames go to the outputs."""

    def __init__(self, g: _Graph, config: VoiceConfig) -> None:
        self.g, self.parts = g, {p.name: p for p in state_parts(config)}
        self.offsets, offset = {}, 0
        for part in state_parts(config):
            self.offsets[part.name] = offset
            offset += part.size
        self.size = offset
        self.kept: list[str] = []
        i64 = np.int64
        self.one_axis = g.const("axis1", np.array([1], i64))
        self.time_axis = g.const("axis2", np.array([2], i64))

    def join(self, name: str, x: str) -> str:
        """State part `name` [B, C, L] joined before `x` [B, C, m]: [B, C, L + m]; records the part's new value."""
        g, part, i64 = self.g, self.parts[name], np.int64
        start = self.offsets[name]
        flat = g.op("Slice", ["state", g.const("start", np.array([start], i64)),
                              g.const("stop", np.array([start + part.size], i64)), self.one_axis], f"{name}.flat")
        kept = g.op("Reshape", [flat, g.const("shape", np.array([-1, part.channels, part.length], i64))],
                    f"{name}.kept")
        joined = g.op("Concat", [kept, x], f"{name}.joined", axis=2)
        first = g.op("Mul", ["keep", g.const("per_frame", np.array([part.per_frame], i64))], f"{name}.first")
        new = g.op("Slice", [joined, first, g.op("Add", [first, g.const("length", np.array([part.length], i64))]),
                             self.time_axis], f"{name}.new")
        self.kept.append(g.op("Flatten", [new], f"{name}.out", axis=1))
        return joined


def _stream_network(g: _Graph, model: VoiceNet) -> tuple[str, int]:
    """Nodes from `audio` [B, n, 640], `state`, `keep` to the clipped ARKit weights [B, n, 52]; returns that
    value's name and the flat state's size."""
    w = _weights(model)
    s = _Stream(g, model.config)
    flat = g.op("Reshape", ["audio", g.const("shape", np.array([0, 1, -1], np.int64))], "signal")  # [B, 1, n F]
    signal = s.join("front", flat)
    spectrum = g.op("Conv", [signal, g.const("front.dft", w["front.dft"])], "spectrum", strides=[HOP])
    power = g.op("Conv", [g.op("Mul", [spectrum, spectrum]), g.const("front.mel", w["front.mel"])], "mel_power")
    logmel = g.op("Mul", [g.op("Log", [g.op("Add", [power, g.const("floor", np.float32(LOG_FLOOR))])]),
                          g.const("log_scale", np.float32(LOG_SCALE))], "logmel")
    x = _silu(g, _conv(g, s.join("input", logmel), w, "input", stride=STEPS_PER_FRAME))
    for k, block in enumerate(model.blocks):
        p = f"blocks.{k}"
        dilation = block.dilated.conv.dilation[0]
        h = _silu(g, _norm(g, x, w, f"{p}.norm"))
        h = _silu(g, _conv(g, s.join(f"{p}.dilated", h), w, f"{p}.dilated.conv", dilation=dilation))
        if block.dilated.pads[1]:  # a block that looks ahead: its residual path waits as long
            joined = s.join(f"{p}.residual", x)
            x = g.op("Slice", [joined, g.const("zero", np.array([0], np.int64)),
                               g.op("Shape", [h], start=2, end=3), s.time_axis], f"{p}.delayed")
        x = g.op("Add", [x, _conv(g, h, w, f"{p}.mix")], f"{p}.out")
    h = _silu(g, _norm(g, x, w, "head_norm"))
    h = _silu(g, _conv(g, s.join("head_conv", h), w, "head_conv.conv"))
    out = g.op("Transpose", [_conv(g, h, w, "head")], "per_frame", perm=[0, 2, 1])
    g.op("Concat", s.kept, output="state_out", axis=1)
    return g.op("Clip", [out, g.const("lo", np.float32(0.0)), g.const("hi", np.float32(1.0))], "weights"), s.size


def _stream_model(g: _Graph, state_size: int, delay: int, outputs: list[tuple[str, int]], doc: str
                  ) -> onnx.ModelProto:
    g.nodes.append(helper.make_node("Constant", [], ["delay_frames"], name="delay_frames",
                                    value=numpy_helper.from_array(np.array([delay], np.int64))))
    inputs = [helper.make_tensor_value_info("audio", TensorProto.FLOAT, ["batch", "frames", SAMPLES_PER_FRAME]),
              helper.make_tensor_value_info("state", TensorProto.FLOAT, ["batch", state_size]),
              helper.make_tensor_value_info("keep", TensorProto.INT64, [1])]
    out = [helper.make_tensor_value_info(name, TensorProto.FLOAT, ["batch", "frames", width])
           for name, width in outputs]
    out += [helper.make_tensor_value_info("state_out", TensorProto.FLOAT, ["batch", state_size]),
            helper.make_tensor_value_info("delay_frames", TensorProto.INT64, [1])]
    graph = helper.make_graph(g.nodes, "voice_stream", inputs, out, g.initializers)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name=STREAM_PRODUCER,
                              doc_string=doc)
    model.ir_version = 8
    onnx.checker.check_model(model, full_check=True)
    return model


def arkit_stream_model(model: VoiceNet, doc: str = "") -> onnx.ModelProto:
    """The ARKit streaming graph: `blendshapes` [B, n, 52] rows."""
    g = _Graph()
    weights, size = _stream_network(g, model)
    g.op("Identity", [weights], output="blendshapes")
    return _stream_model(g, size, delay_frames(model.config), [("blendshapes", model.config.outputs)], doc)


def flame_stream_model(model: VoiceNet, expression_map: np.ndarray, jaw_map: np.ndarray, doc: str = ""
                       ) -> onnx.ModelProto:
    """The FLAME streaming graph: `expression` [B, n, E] and `jaw_pose` [B, n, 3] rows."""
    g = _Graph()
    weights, size = _stream_network(g, model)
    g.op("MatMul", [weights, g.const("expression_map", expression_map.astype(np.float32))], output="expression")
    g.op("MatMul", [weights, g.const("jaw_map", jaw_map.astype(np.float32))], output="jaw_pose")
    return _stream_model(g, size, delay_frames(model.config),
                         [("expression", expression_map.shape[1]), ("jaw_pose", 3)], doc)


def _base_name(name: str) -> str:
    """An initializer's module name: onnx_graph.py suffixes each with `_<count>`."""
    return re.sub(r"_\d+$", "", name)


def is_voice_graph(model: onnx.ModelProto) -> bool:
    """Whether `model` is the built-in voice's windowed graph (written by onnx_graph.py)."""
    return model.producer_name == PRODUCER and any(i.name.startswith("blocks.0.dilated.conv.weight")
                                                   for i in model.graph.initializer)


def stream_model_of(model: onnx.ModelProto) -> onnx.ModelProto | None:
    """The streaming graph of a built-in voice's windowed graph (ARKit or FLAME head, with the maps it holds now);
    None for any other audio model (a user's own: its layers are unknown, so it is only run windowed)."""
    if not is_voice_graph(model):
        return None
    weights = {_base_name(i.name): numpy_helper.to_array(i) for i in model.graph.initializer}
    convs = {_base_name(n.input[1]): n for n in model.graph.node if n.op_type == "Conv" and len(n.input) > 1}
    blocks = []
    while f"blocks.{len(blocks)}.dilated.conv.weight" in weights:
        node = convs[f"blocks.{len(blocks)}.dilated.conv.weight"]
        attrs = {a.name: helper.get_attribute_value(a) for a in node.attribute}
        dilation = int(attrs.get("dilations", [1])[0])
        blocks.append((dilation, int(attrs.get("pads", [0, 0])[1]) // dilation))
    channels, _, _ = weights["input.weight"].shape
    net = VoiceNet(VoiceConfig(channels=int(channels), blocks=tuple(blocks),
                               outputs=int(weights["head.weight"].shape[0])))
    state = {key: torch.from_numpy(np.array(weights[key]).reshape(value.shape))
             for key, value in net.state_dict().items()}
    net.load_state_dict(state)
    if "expression_map" in weights:
        return flame_stream_model(net, weights["expression_map"], weights["jaw_map"], model.doc_string)
    return arkit_stream_model(net, model.doc_string)


__all__ = ["FRONT_STATE", "INPUT_STATE", "STREAM_PRODUCER", "StatePart", "arkit_stream_model", "delay_frames",
           "flame_stream_model", "is_voice_graph", "state_parts", "stream_model_of"]
