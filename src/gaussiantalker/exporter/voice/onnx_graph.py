"""The voice network as an ONNX graph, built node by node at opset 17 (docs/voice.md, "The model files").

Built by hand rather than traced: torch's exporter writes opset 18 or later, and the graph must run in
onnxruntime-web as well, so it uses only long-standing standard ops (Shape, Gather, Div, Mul, Max, Pad, Slice,
Unsqueeze, Conv, Log, Sigmoid, ReduceMean, Sqrt, Transpose, Clip, MatMul) and no custom op. `tests/test_voice.py`
checks it against the torch network.

Two heads over the same network:
* ARKit (`arkit_model`): input `audio` float32 [1, S] at 16 kHz -> `blendshapes` float32 [1, T, 52] in
  ARKIT_BLENDSHAPES order, clipped to 0..1, T = max(1, round(S / 640)) frames at 25 fps.
* FLAME (`flame_model`): the same weights w, then `expression` [1, T, E] = w @ M and `jaw_pose` [1, T, 3] =
  w @ J: M [52, E] maps the ARKit mouth onto FLAME expression coefficients (flame_fit.py), J turns jawOpen into
  a rotation about x. For S a multiple of 640, T = S / 640, the SDK translator graph's contract.
"""

from __future__ import annotations

import numpy as np
import onnx
import torch
from onnx import TensorProto, helper, numpy_helper

from ..export.onnx_build import OPSET, VOICE_PRODUCER, Graph, channel_norm, conv, silu
from .model import (
    HOP,
    LOG_FLOOR,
    LOG_SCALE,
    NORM_EPS,
    SAMPLES_PER_FRAME,
    SILENCE_AFTER,
    SILENCE_BEFORE,
    STEPS_PER_FRAME,
    FrontEnd,
    VoiceNet,
)

PRODUCER = VOICE_PRODUCER


def _weights(module: torch.nn.Module) -> dict[str, np.ndarray]:
    return {key: value.detach().cpu().numpy().astype(np.float32) for key, value in module.state_dict().items()}


def _norm(g: Graph, x: str, weights: dict, prefix: str) -> str:
    return channel_norm(g, x, weights, prefix, NORM_EPS)


def _network(g: Graph, model: VoiceNet, audio: str) -> str:
    """Nodes from `audio` [1, S] to the clipped ARKit weights [1, T, 52]; returns that value's name."""
    w = _weights(model)
    i64 = np.int64
    # T = max(1, (S + 320) div 640); audio padded with 640 zeros, then cut to T * 640
    samples = g.op("Gather", [g.op("Shape", [audio]), g.const("axis1", np.array(1, i64))], "samples", axis=0)
    half = g.const("half_frame", np.array(SAMPLES_PER_FRAME // 2, i64))
    spf = g.const("samples_per_frame", np.array(SAMPLES_PER_FRAME, i64))
    frames = g.op("Max", [g.op("Div", [g.op("Add", [samples, half]), spf]), g.const("one", np.array(1, i64))],
                  "frames")
    length = g.op("Unsqueeze", [g.op("Mul", [frames, spf]), g.const("axes0", np.array([0], i64))], "length")
    padded = g.op("Pad", [audio, g.const("pad_end", np.array([0, 0, 0, SAMPLES_PER_FRAME], i64))], "padded")
    fitted = g.op("Slice", [padded, g.const("zero", np.array([0], i64)), length, g.const("axis", np.array([1], i64))],
                  "fitted")
    silence = g.const("silence", np.array([0, SILENCE_BEFORE * SAMPLES_PER_FRAME, 0,
                                           SILENCE_AFTER * SAMPLES_PER_FRAME], i64))
    x = g.op("Unsqueeze", [g.op("Pad", [fitted, silence], "silenced"), g.const("axes1", np.array([1], i64))],
             "signal")  # [1, 1, L + silence]
    # log-mel front end
    spectrum = g.op("Conv", [x, g.const("front.dft", w["front.dft"])], "spectrum", strides=[HOP],
                    pads=list(FrontEnd.padding()))
    power = g.op("Conv", [g.op("Mul", [spectrum, spectrum]), g.const("front.mel", w["front.mel"])], "mel_power")
    logmel = g.op("Mul", [g.op("Log", [g.op("Add", [power, g.const("floor", np.float32(LOG_FLOOR))])]),
                          g.const("log_scale", np.float32(LOG_SCALE))], "logmel")
    # network
    half_steps = STEPS_PER_FRAME // 2
    x = silu(g, conv(g, logmel, w, "input", (half_steps, half_steps), stride=STEPS_PER_FRAME))
    for k, block in enumerate(model.blocks):
        p = f"blocks.{k}"
        h = silu(g, _norm(g, x, w, f"{p}.norm"))
        h = silu(g, conv(g, h, w, f"{p}.dilated.conv", block.dilated.pads, dilation=block.dilated.conv.dilation[0]))
        x = g.op("Add", [x, conv(g, h, w, f"{p}.mix")], f"{p}.out")
    h = silu(g, _norm(g, x, w, "head_norm"))
    h = silu(g, conv(g, h, w, "head_conv.conv", model.head_conv.pads))
    out = g.op("Transpose", [conv(g, h, w, "head")], "per_frame", perm=[0, 2, 1])
    out = g.op("Slice", [out, g.const("first", np.array([SILENCE_BEFORE], i64)),
                         g.const("last", np.array([-SILENCE_AFTER], i64)), g.const("axis", np.array([1], i64))],
               "frames_kept")
    return g.op("Clip", [out, g.const("lo", np.float32(0.0)), g.const("hi", np.float32(1.0))], "weights")


def _model(g: Graph, outputs: list[tuple[str, int]], doc: str) -> onnx.ModelProto:
    graph = helper.make_graph(
        g.nodes, "voice", [helper.make_tensor_value_info("audio", TensorProto.FLOAT, [1, "samples"])],
        [helper.make_tensor_value_info(name, TensorProto.FLOAT, [1, "frames", width]) for name, width in outputs],
        g.initializers)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name=PRODUCER,
                              doc_string=doc)
    model.ir_version = 8  # opset 17's IR version: readable by onnxruntime 1.13 and later
    onnx.checker.check_model(model, full_check=True)
    return model


def arkit_model(model: VoiceNet, doc: str = "") -> onnx.ModelProto:
    """The ARKit graph: `audio` [1, S] -> `blendshapes` [1, T, 52]."""
    g = Graph()
    weights = _network(g, model, "audio")
    g.op("Identity", [weights], output="blendshapes")
    return _model(g, [("blendshapes", model.config.outputs)], doc)


def flame_model(model: VoiceNet, expression_map: np.ndarray, jaw_map: np.ndarray, doc: str = "") -> onnx.ModelProto:
    """The FLAME graph: `audio` [1, S] -> `expression` [1, T, E] (weights @ expression_map [52, E]) and
    `jaw_pose` [1, T, 3] (weights @ jaw_map [52, 3])."""
    g = Graph()
    weights = _network(g, model, "audio")
    g.op("MatMul", [weights, g.const("expression_map", expression_map.astype(np.float32))], output="expression")
    g.op("MatMul", [weights, g.const("jaw_map", jaw_map.astype(np.float32))], output="jaw_pose")
    return _model(g, [("expression", expression_map.shape[1]), ("jaw_pose", 3)], doc)


def expression_map_of(model: onnx.ModelProto) -> np.ndarray:
    """The [52, E] expression map a FLAME graph holds."""
    for tensor in model.graph.initializer:
        if tensor.name.startswith("expression_map"):
            return numpy_helper.to_array(tensor)
    raise ValueError("not a voice FLAME graph: it has no expression_map")


def _replace(model: onnx.ModelProto, prefix: str, value: np.ndarray) -> onnx.ModelProto:
    """A copy of a FLAME graph with its initializer `prefix*` replaced by `value` (float32)."""
    out = onnx.ModelProto.FromString(model.SerializeToString())
    for tensor in out.graph.initializer:
        if tensor.name.startswith(prefix):
            tensor.CopyFrom(numpy_helper.from_array(np.asarray(value, np.float32), tensor.name))
            return out
    raise ValueError(f"not a voice FLAME graph: it has no {prefix}")


def with_expression_map(model: onnx.ModelProto, expression_map: np.ndarray) -> onnx.ModelProto:
    """A copy of a FLAME graph with another expression map [52, E] (E may differ: the output's width follows)."""
    out = _replace(model, "expression_map", expression_map)
    for value in out.graph.output:
        if value.name == "expression":
            value.type.tensor_type.shape.dim[2].dim_value = int(expression_map.shape[1])
    onnx.checker.check_model(out, full_check=True)
    return out


def with_jaw_map(model: onnx.ModelProto, jaw_map: np.ndarray) -> onnx.ModelProto:
    """A copy of a FLAME graph with another jaw map [52, 3]."""
    out = _replace(model, "jaw_map", jaw_map)
    onnx.checker.check_model(out, full_check=True)
    return out


__all__ = ["OPSET", "arkit_model", "expression_map_of", "flame_model", "with_expression_map", "with_jaw_map"]
