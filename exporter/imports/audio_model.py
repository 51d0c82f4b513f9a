"""An audio model attached to an imported speaker, so audio drives it (docs/import.md, "Audio models").

Any model of the speaker's signature fits: one float32 input [1, S], mono audio at the speaker's sample rate, and
* for an ARKit speaker (LAM's audio-to-expression model exported to ONNX, or another) a float32 output [1, T, 52],
  ARKit weights in ARKIT_BLENDSHAPES order, T frames for the S samples at the speaker's fps (another T is resampled
  linearly in time), renamed `blendshapes`;
* for a FLAME speaker (an imported GaussianAvatars avatar) two float32 outputs [1, T, E] and [1, T, 3], the
  expression coefficients and jaw pose (axis-angle), S a multiple of the speaker's samples per frame and
  T = S / samples per frame, as the SDK's own translator graph; renamed `expression` and `jaw_pose`.
The input is renamed `audio`: these are the names the bundle's `translator` graph has.
"""

from __future__ import annotations

import os
from pathlib import Path

import onnx

from gaussiantalker.sdk.errors import ImportFormatError
from gaussiantalker.sdk.rig import ARKIT_COUNT

AUDIO_INPUT, BLENDSHAPE_OUTPUT = "audio", "blendshapes"
# The outputs a model must have, per rig: (name in the bundle, last-axis width or None for any, what it holds).
ARKIT_OUTPUTS = ((BLENDSHAPE_OUTPUT, ARKIT_COUNT, "ARKit weights"),)


def flame_outputs(n_expr: int) -> tuple[tuple[str, int, str], ...]:
    """The outputs of an audio-to-FLAME model for a speaker of `n_expr` expression coefficients."""
    return (("expression", n_expr, "expression coefficients"), ("jaw_pose", 3, "jaw pose"))


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


def load_audio_model(path: str | os.PathLike, outputs: tuple[tuple[str, int, str], ...] = ARKIT_OUTPUTS) -> bytes:
    """The model file checked (one float32 [1, S] input; float32 [1, T, width] first outputs, one per `outputs`
    entry) and its input and outputs renamed; ImportFormatError naming the file and what does not fit."""
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
    if len(graph.output) < len(outputs):
        raise ImportFormatError(f"audio model {path}: has {len(graph.output)} output(s); needs "
                                f"{', '.join(f'{what} [1, T, {width}]' for _, width, what in outputs)}")
    audio = inputs[0]
    float32 = onnx.TensorProto.FLOAT
    if audio.type.tensor_type.elem_type != float32 or len(_dims(audio)) != 2:
        raise ImportFormatError(f"audio model {path}: input {audio.name!r} must be float32 [1, S], got "
                                f"{onnx.TensorProto.DataType.Name(audio.type.tensor_type.elem_type)} {_dims(audio)}")
    for value, (_, width, what) in zip(graph.output, outputs, strict=False):
        dims = _dims(value)
        if value.type.tensor_type.elem_type != float32 or len(dims) != 3 or dims[2] not in (width, None):
            raise ImportFormatError(f"audio model {path}: output {value.name!r} must be float32 [1, T, {width}] "
                                    f"{what}, got {dims}")
    _rename(graph, audio.name, AUDIO_INPUT)
    for value, (name, _, _) in zip(list(graph.output), outputs, strict=False):
        _rename(graph, value.name, name)
    del graph.output[len(outputs):]
    return model.SerializeToString()


__all__ = ["ARKIT_OUTPUTS", "AUDIO_INPUT", "BLENDSHAPE_OUTPUT", "flame_outputs", "load_audio_model"]
