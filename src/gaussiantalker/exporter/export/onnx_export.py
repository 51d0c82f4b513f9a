"""torch module -> ONNX graph whose weights become bundle buffers (runtime/onnxruntime_backend.py does the reverse)."""

from __future__ import annotations

import contextlib
import io
import logging
import re
import warnings
from collections.abc import Callable, Iterator

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


def export_onnx(module: torch.nn.Module, args: tuple, input_names: list[str], output_names: list[str],
                dynamic_shapes: dict | None = None) -> onnx.ModelProto:
    """Export with torch.onnx's dynamo exporter, quietly, and return the model proto.

    optimize=False on purpose: the exporter's graph optimizer rewrites `x + eps` to `x` for tiny eps (1e-16,
    1e-12, even 1e-8 were dropped in torch 2.13), which silently strips the contract's epsilon guards and turns a
    zero rotation into NaN. onnxruntime constant-folds and fuses the graph itself when it loads it.
    """
    module.eval()
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
