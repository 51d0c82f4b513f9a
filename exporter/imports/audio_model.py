"""An audio-to-ARKit ONNX model attached to an ARKit speaker, so audio drives it (docs/import.md, "Audio models").

Any model of this signature fits (LAM's audio-to-expression model exported to ONNX, or another): one float32
input [1, S], mono audio at the speaker's sample rate, and a float32 output [1, T, 52], ARKit weights in
ARKIT_BLENDSHAPES order, T frames for the S samples at the speaker's fps (another T is resampled linearly in time).
The importer renames them `audio` and `blendshapes`, the names the bundle's `translator` graph has.
"""

from __future__ import annotations

import os
from pathlib import Path

import onnx

from gaussiantalker.sdk.errors import ImportFormatError
from gaussiantalker.sdk.rig import ARKIT_COUNT

AUDIO_INPUT, BLENDSHAPE_OUTPUT = "audio", "blendshapes"


def _rename(graph: onnx.GraphProto, old: str, new: str) -> None:
    """Rename value `old` to `new` everywhere in the graph (inputs, outputs, node edges, value infos)."""
    for value in list(graph.input) + list(graph.output) + list(graph.value_info):
        if value.name == old:
            value.name = new
    for node in graph.node:
        node.input[:] = [new if name == old else name for name in node.input]
        node.output[:] = [new if name == old else name for name in node.output]


def _dims(value: onnx.ValueInfoProto) -> list:
    return [d.dim_param or (d.dim_value if d.HasField("dim_value") else None) for d in
            value.type.tensor_type.shape.dim]


def load_audio_model(path: str | os.PathLike) -> bytes:
    """The model file checked (one float32 [1, S] input, a float32 [1, T, 52] first output) and its input and
    output renamed `audio` and `blendshapes`; ImportFormatError naming the file and what does not fit."""
    path = Path(path)
    try:
        model = onnx.load(str(path))
        onnx.checker.check_model(model)
    except Exception as exc:  # onnx raises assorted errors on unreadable or invalid models
        raise ImportFormatError(f"audio model {path}: not a valid ONNX model: {exc}") from None
    graph = model.graph
    initializers = {init.name for init in graph.initializer}
    inputs = [value for value in graph.input if value.name not in initializers]
    if len(inputs) != 1:
        raise ImportFormatError(f"audio model {path}: needs exactly one input (audio [1, S]), has "
                                f"{[v.name for v in inputs]}")
    if not graph.output:
        raise ImportFormatError(f"audio model {path}: has no output")
    audio, weights = inputs[0], graph.output[0]
    float32 = onnx.TensorProto.FLOAT
    if audio.type.tensor_type.elem_type != float32 or len(_dims(audio)) != 2:
        raise ImportFormatError(f"audio model {path}: input {audio.name!r} must be float32 [1, S], got "
                                f"{onnx.TensorProto.DataType.Name(audio.type.tensor_type.elem_type)} {_dims(audio)}")
    dims = _dims(weights)
    if weights.type.tensor_type.elem_type != float32 or len(dims) != 3 or dims[2] not in (ARKIT_COUNT, None):
        raise ImportFormatError(f"audio model {path}: output {weights.name!r} must be float32 [1, T, "
                                f"{ARKIT_COUNT}] ARKit weights, got {dims}")
    _rename(graph, audio.name, AUDIO_INPUT)
    _rename(graph, weights.name, BLENDSHAPE_OUTPUT)
    del graph.output[1:]
    return model.SerializeToString()


__all__ = ["AUDIO_INPUT", "BLENDSHAPE_OUTPUT", "load_audio_model"]
