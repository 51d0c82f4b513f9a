"""An audio model attached to an imported speaker, so audio drives it (docs/import.md, "Audio models").

Any model of the speaker's signature fits: one float32 input [1, S], mono audio at the speaker's sample rate, and
* for an ARKit speaker (LAM's audio-to-expression model exported to ONNX, or another) a float32 output [1, T, 52],
  ARKit weights in ARKIT_BLENDSHAPES order, T frames for the S samples at the speaker's fps (another T is resampled
  linearly in time), renamed `blendshapes`;
* for a FLAME speaker (an imported GaussianAvatars avatar) two float32 outputs [1, T, E] and [1, T, 3], the
  expression coefficients and jaw pose (axis-angle), S a multiple of the speaker's samples per frame and
  T = S / samples per frame, as the SDK's own translator graph; renamed `expression` and `jaw_pose`.
The input is renamed `audio`: these are the names the bundle's `translator` graph has.

The model file is the user's (docs/untrusted-input.md, "Audio models"): its size is bounded, and external tensor
data is read only from files inside the model's own folder (no absolute paths, no '..', no link leading out),
since the model's bytes, external data included, are copied into the checkpoint and the bundle.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from itertools import chain
from pathlib import Path

import onnx

from gaussiantalker.sdk.errors import ImportFormatError
from gaussiantalker.sdk.rig import ARKIT_COUNT

AUDIO_INPUT, BLENDSHAPE_OUTPUT = "audio", "blendshapes"
# The outputs a model must have, per rig: (name in the bundle, last-axis width or None for any, what it holds).
ARKIT_OUTPUTS = ((BLENDSHAPE_OUTPUT, ARKIT_COUNT, "ARKit weights"),)
# A model, external data included, must fit one protobuf (the checkpoint and the bundle store it as one).
MAX_MODEL_BYTES = 2**31 - 1


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


def _tensors(graph: onnx.GraphProto) -> Iterator[onnx.TensorProto]:
    """Every tensor a graph holds: its initializers, and the tensors of its nodes' attributes."""
    yield from graph.initializer
    yield from _node_tensors(graph.node)


def _node_tensors(nodes) -> Iterator[onnx.TensorProto]:
    """The tensors in nodes' attributes, subgraphs included."""
    for node in nodes:
        for attribute in node.attribute:
            if attribute.HasField("t"):
                yield attribute.t
            yield from attribute.tensors
            for sub in ([attribute.g] if attribute.HasField("g") else []) + list(attribute.graphs):
                yield from _tensors(sub)


def _external_data(model: onnx.ModelProto, path: Path) -> None:
    """Load the model's external tensor data, refusing a location outside the model's folder (ImportFormatError)."""
    folder = path.resolve().parent
    total = path.stat().st_size
    tensors = chain(_tensors(model.graph), *(_node_tensors(function.node) for function in model.functions))
    for tensor in tensors:
        if tensor.data_location != onnx.TensorProto.EXTERNAL:
            continue
        location = next((entry.value for entry in tensor.external_data if entry.key == "location"), "")
        target = (folder / location).resolve()
        inside = bool(location) and not Path(location).is_absolute() and ".." not in Path(location).parts \
            and "\\" not in location and folder in target.parents and target.is_file()
        if not inside:
            raise ImportFormatError(f"audio model {path}: tensor {tensor.name[:60]!r} keeps its data in "
                                    f"{location[:120]!r}, which is not a file inside the model's folder")
        total += target.stat().st_size
        if total > MAX_MODEL_BYTES:
            raise ImportFormatError(f"audio model {path}: with its external data it is over {MAX_MODEL_BYTES} bytes")
    onnx.load_external_data_for_model(model, str(folder))


def _one_line(exc: BaseException) -> str:
    """onnx's multi-line messages as one short line."""
    return " ".join(str(exc).split())[:300] or type(exc).__name__


def load_audio_model(path: str | os.PathLike, outputs: tuple[tuple[str, int, str], ...] = ARKIT_OUTPUTS) -> bytes:
    """The model file checked (one float32 [1, S] input; float32 [1, T, width] first outputs, one per `outputs`
    entry) and its input and outputs renamed; ImportFormatError naming the file and what does not fit."""
    path = Path(path)
    if not path.is_file():
        raise ImportFormatError(f"audio model {path} does not exist")
    if path.stat().st_size > MAX_MODEL_BYTES:
        raise ImportFormatError(f"audio model {path} is {path.stat().st_size} bytes, over ONNX's {MAX_MODEL_BYTES}")
    try:
        model = onnx.load(str(path), load_external_data=False)
        _external_data(model, path)
        onnx.checker.check_model(model)
    except ImportFormatError:
        raise
    except Exception as exc:  # onnx raises assorted errors on unreadable or invalid models
        raise ImportFormatError(f"audio model {path}: not a valid ONNX model: {_one_line(exc)}") from None
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
