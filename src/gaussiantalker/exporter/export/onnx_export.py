"""torch module -> ONNX graph whose weights become bundle buffers (runtime/onnxruntime_backend.py does the reverse)."""

from __future__ import annotations

import contextlib
import hashlib
import io
import logging
import re
import warnings
from collections.abc import Callable, Iterator
from itertools import chain

import numpy as np
import onnx
import torch
from onnx import external_data_helper, numpy_helper

from gaussiantalker.sdk.bundle import BundleWriter
from gaussiantalker.sdk.codecs import ONNX_DTYPES

from .presets import stored_sparse

# Initializers at least this large move out of the graph into buffers; tiny ones (shape constants, which
# ONNX shape inference must see) stay inline.
EXTERNALIZE_MIN_BYTES = 1024


@contextlib.contextmanager
def quiet_logger(name: str) -> Iterator[None]:
    """Raise one logger's level to ERROR for the duration of a call, then restore it (global state untouched)."""
    logger = logging.getLogger(name)
    previous = logger.level
    logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        logger.setLevel(previous)


# Graphs exported inside a `reused_exports()` block, by everything that determines them (`_export_key`): serialised
# protos, at most this many bytes in all. A bench that exports one speaker under many settings (gt-bench sweep,
# codings) traces the same translator graphs again and again, each a torch.onnx export of seconds to minutes.
# Outside such a block nothing is kept and every export traces afresh.
_reused: dict[str, bytes] | None = None
REUSED_EXPORTS_MAX_BYTES = 1 << 30


@contextlib.contextmanager
def reused_exports() -> Iterator[None]:
    """Within the block, an export whose module, inputs and names equal an earlier one's in the block gets a copy
    of that graph instead of a new trace (the same proto: torch.onnx traces the same module to the same graph)."""
    global _reused
    outer = _reused
    _reused = {} if outer is None else outer
    try:
        yield
    finally:
        _reused = outer


def _export_key(module: torch.nn.Module, args: tuple, *names) -> str:
    """A digest of what an export depends on: every submodule's class and plain attributes (an object without a
    value repr shows its address, so it never matches another), every parameter's and buffer's values, the
    example inputs, the names and the dynamic shapes."""
    digest = hashlib.sha256()

    def tensor(value: torch.Tensor) -> None:
        value = value.detach().cpu().contiguous()
        digest.update(repr((value.dtype, tuple(value.shape))).encode())
        digest.update(value.view(torch.uint8).numpy().tobytes() if value.numel() else b"")

    for prefix, sub in module.named_modules():
        digest.update(repr((prefix, type(sub).__module__, type(sub).__qualname__)).encode())
        for key, value in sorted(vars(sub).items()):
            if key in ("_parameters", "_buffers", "_modules"):
                continue
            digest.update(key.encode())
            if isinstance(value, torch.Tensor):
                tensor(value)
            elif isinstance(value, np.ndarray):
                tensor(torch.from_numpy(np.ascontiguousarray(value)))
            else:
                digest.update(repr(value).encode())
    for name, value in chain(module.named_parameters(), module.named_buffers()):
        digest.update(name.encode())
        tensor(value)
    for value in args:
        if isinstance(value, torch.Tensor):
            tensor(value)
        else:
            digest.update(repr(value).encode())
    digest.update(repr(names).encode())
    return digest.hexdigest()


def export_onnx(module: torch.nn.Module, args: tuple, input_names: list[str], output_names: list[str],
                dynamic_shapes: dict | None = None) -> onnx.ModelProto:
    """Export with torch.onnx's dynamo exporter, quietly, and return the model proto (in a `reused_exports()`
    block, a copy of the same export's earlier proto).

    optimize=False on purpose: the exporter's graph optimizer rewrites `x + eps` to `x` for tiny eps (1e-16,
    1e-12, even 1e-8 were dropped in torch 2.13), which silently strips the contract's epsilon guards and turns a
    zero rotation into NaN. onnxruntime constant-folds and fuses the graph itself when it loads it.
    """
    module.eval()
    reused = _reused
    if reused is None:
        return _traced(module, args, input_names, output_names, dynamic_shapes)
    key = _export_key(module, args, input_names, output_names, dynamic_shapes)
    if key in reused:
        return onnx.ModelProto.FromString(reused[key])
    model = _traced(module, args, input_names, output_names, dynamic_shapes)
    serialised = model.SerializeToString()
    if sum(map(len, reused.values())) + len(serialised) <= REUSED_EXPORTS_MAX_BYTES:
        reused[key] = serialised
    return model


def _traced(module: torch.nn.Module, args: tuple, input_names: list[str], output_names: list[str],
            dynamic_shapes: dict | None) -> onnx.ModelProto:
    """One torch.onnx export (`export_onnx`), checked."""
    with quiet_logger("torch.onnx"), warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()), \
            torch.no_grad():
        warnings.simplefilter("ignore")
        program = torch.onnx.export(module, args, dynamo=True, input_names=input_names,
                                    output_names=output_names, dynamic_shapes=dynamic_shapes, verbose=False,
                                    optimize=False)
    model = program.model_proto
    onnx.checker.check_model(model)
    return model


def _value_info(value: onnx.ValueInfoProto) -> dict:
    tensor = value.type.tensor_type
    shape = [d.dim_param if d.dim_param else int(d.dim_value) for d in tensor.shape.dim]
    return {"name": value.name, "dtype": ONNX_DTYPES.get(tensor.elem_type, str(tensor.elem_type)), "shape": shape}


def strip_debug_metadata(model: onnx.ModelProto) -> None:
    """Drop the exporter's per-node debug annotations (source stack traces, torch names): most of a graph's bytes
    (docs/bundle-format.md, "Graphs"), never read by a runtime. Node names, shapes and semantics are untouched."""
    graphs = [model.graph]
    while graphs:
        graph = graphs.pop()
        graph.doc_string = ""
        for node in graph.node:
            del node.metadata_props[:]
            node.doc_string = ""
            for attr in node.attribute:  # control-flow subgraphs (If/Loop/Scan) carry annotations too
                if attr.HasField("g"):
                    graphs.append(attr.g)
                graphs.extend(attr.graphs)
        for value in (*graph.input, *graph.output, *graph.value_info):
            del value.metadata_props[:]
            value.doc_string = ""


def add_graph(writer: BundleWriter, graph_name: str, model: onnx.ModelProto,
              codec_for: Callable[[str, np.ndarray], tuple[str, int | None]] = lambda buffer, array: ("raw", None),
              share: bool = False) -> dict:
    """Move the model's large initializers into bundle buffers named `graph_name/...` (each stored with the
    (codec, chunk) `codec_for(buffer name, array)` picks) and store the graph. `share`: an initializer whose values
    and coding a buffer already added holds points at that buffer instead (a streaming graph beside its windowed
    one: the same weights, stored once)."""
    model = onnx.ModelProto.FromString(model.SerializeToString())  # never mutate the caller's proto
    strip_debug_metadata(model)
    initializers: dict[str, str] = {}
    for tensor in model.graph.initializer:
        array = numpy_helper.to_array(tensor)
        if array.nbytes < EXTERNALIZE_MIN_BYTES:
            continue
        buffer_name = f"{graph_name}/{re.sub(r'[^A-Za-z0-9_.]+', '_', tensor.name)}"
        codec, chunk = codec_for(buffer_name, array)
        sparse = stored_sparse(buffer_name, array)
        shared = writer.find_buffer(array, codec, chunk, sparse) if share else None
        if shared is not None:
            buffer_name = shared
        else:
            writer.add_buffer(buffer_name, array, codec=codec, chunk=chunk, sparse=sparse)
        external_data_helper.set_external_data(tensor, location="bundle", offset=0, length=array.nbytes)
        tensor.ClearField("raw_data")
        for field in ("float_data", "int64_data", "int32_data", "double_data"):
            tensor.ClearField(field)
        tensor.data_location = onnx.TensorProto.EXTERNAL
        initializers[tensor.name] = buffer_name
    inputs = [_value_info(v) for v in model.graph.input]
    outputs = [_value_info(v) for v in model.graph.output]
    writer.add_graph(graph_name, model.SerializeToString(), inputs, outputs, initializers)
    return {"inputs": inputs, "outputs": outputs, "initializers": initializers}
