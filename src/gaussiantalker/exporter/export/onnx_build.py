"""Small helpers for ONNX graphs built node by node (the built-in voice's windowed and streaming graphs): value
names kept unique, initializers, and the few layer shapes those graphs repeat. Built by hand rather than traced
where a graph must stay at opset 17 for onnxruntime-web (docs/voice.md, "The model files")."""

from __future__ import annotations

import numpy as np
import onnx
from onnx import helper, numpy_helper

OPSET = 17
# The producer name of the built-in voice's graphs (exporter/voice/onnx_graph.py): how an attached audio model is
# recognised as the built-in voice, whose streaming form the exporter can build (voice_stream.py).
VOICE_PRODUCER = "gaussiantalker voice"


class Graph:
    """Nodes and initializers under construction, with unique value names."""

    def __init__(self) -> None:
        self.nodes: list[onnx.NodeProto] = []
        self.initializers: list[onnx.TensorProto] = []
        self.count = 0

    def name(self, hint: str) -> str:
        self.count += 1
        return f"{hint}_{self.count}"

    def const(self, hint: str, value) -> str:
        name = self.name(hint)
        self.initializers.append(numpy_helper.from_array(np.asarray(value), name))
        return name

    def op(self, op_type: str, inputs: list[str], hint: str | None = None, output: str | None = None,
           **attributes) -> str:
        out = output or self.name(hint or op_type.lower())
        self.nodes.append(helper.make_node(op_type, inputs, [out], name=self.name(op_type), **attributes))
        return out


def conv(g: Graph, x: str, weights: dict, prefix: str, pads: tuple[int, int] = (0, 0), stride: int = 1,
         dilation: int = 1) -> str:
    """Conv1d with `weights[prefix.weight]` and `.bias`."""
    w = g.const(f"{prefix}.weight", weights[f"{prefix}.weight"])
    b = g.const(f"{prefix}.bias", weights[f"{prefix}.bias"])
    return g.op("Conv", [x, w, b], prefix, pads=list(pads), strides=[stride], dilations=[dilation])


def silu(g: Graph, x: str) -> str:
    return g.op("Mul", [x, g.op("Sigmoid", [x])], "silu")


def channel_norm(g: Graph, x: str, weights: dict, prefix: str, eps: float, axis: int = 1) -> str:
    """Normalisation over channels (`axis`: 1 for [B, C, T], -1 for channels last) at each step, then `prefix`'s
    per-channel scale and shift."""
    mean = g.op("ReduceMean", [x], "mean", axes=[axis], keepdims=1)
    centred = g.op("Sub", [x, mean], "centred")
    var = g.op("ReduceMean", [g.op("Mul", [centred, centred])], "var", axes=[axis], keepdims=1)
    std = g.op("Sqrt", [g.op("Add", [var, g.const("eps", np.float32(eps))])], "std")
    scaled = g.op("Div", [centred, std], "scaled")
    # The scale and shift are stored [1, C, 1] either way (a bundle stores a stream's copy once, by content) and
    # laid along the last axis by a node onnxruntime folds when it loads the graph.
    gamma, beta = (g.const(f"{prefix}.{name}", np.asarray(weights[f"{prefix}.{name}"]).reshape(1, -1, 1))
                   for name in ("weight", "bias"))
    if axis != 1:
        last = g.const("shape", np.array([1, 1, -1], np.int64))
        gamma, beta = (g.op("Reshape", [value, last], f"{prefix}.channels_last") for value in (gamma, beta))
    return g.op("Add", [g.op("Mul", [scaled, gamma]), beta], prefix)


__all__ = ["OPSET", "VOICE_PRODUCER", "Graph", "channel_norm", "conv", "silu"]
