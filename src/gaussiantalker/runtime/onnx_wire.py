"""A minimal reader of the ONNX protobuf wire format: every tensor's name, dims, dtype and external-data flag.

The bundle checks (runtime/bundle_checks.py) need only these four fields of each TensorProto, to refuse a graph
whose initializers do not match the buffers fed to them before onnxruntime sees it. This walk stays instead of
the `onnx` package because onnx is not otherwise a runtime dependency and adding it would grow a runtime-only
install for those four fields; docs/bundle-format.md ("Graphs", "Why the runtime reads the protobuf itself") gives
the measured size it would add.

Field numbers from onnx.proto: ModelProto.graph 7, .functions 25; FunctionProto.node 7; GraphProto.node 1,
.initializer 5, .sparse_initializer 15; NodeProto.attribute 5; AttributeProto.t 5, .g 6, .tensors 10, .graphs 11,
.sparse_tensor 22, .sparse_tensors 23; SparseTensorProto.values 1, .indices 2; TensorProto.dims 1, .data_type 2,
.name 8, .data_location 14 (1 = EXTERNAL).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

# The deepest a message may sit below the ModelProto (a graph is 1, its node 2, a node's attribute 3, a subgraph of
# that attribute 4, ...): protobuf's own parsers, onnxruntime's included, refuse a model nested deeper, so no
# loadable model is refused, and the walk's recursion stays bounded whatever the bytes say (docs/untrusted-input.md,
# "Bundles").
MAX_MESSAGE_DEPTH = 100


@dataclass
class TensorInfo:
    """What the bundle checks read of one TensorProto; `top_level`: an initializer of the model's main graph."""

    name: str
    dims: list[int]
    data_type: int
    external: bool
    top_level: bool


def _varint(data: memoryview, pos: int) -> tuple[int, int]:
    result = shift = 0
    while True:
        if pos >= len(data) or shift > 63:
            raise ValueError("truncated or oversized varint")
        byte = data[pos]
        pos += 1
        result |= (byte & 0x7F) << shift
        if byte < 0x80:
            return result, pos
        shift += 7


def _fields(data: memoryview) -> Iterator[tuple[int, int, int | memoryview]]:
    """(field number, wire type, value) of one protobuf message; length-delimited values are zero-copy views."""
    pos = 0
    while pos < len(data):
        key, pos = _varint(data, pos)
        wire = key & 7
        if wire == 0:
            value, pos = _varint(data, pos)
        elif wire in (1, 5):
            size = 8 if wire == 1 else 4
            value, pos = data[pos:pos + size], pos + size
        elif wire == 2:
            size, pos = _varint(data, pos)
            value, pos = data[pos:pos + size], pos + size
        else:
            raise ValueError(f"unsupported protobuf wire type {wire}")
        if pos > len(data):
            raise ValueError("a field runs past the end of its message")
        yield key >> 3, wire, value


def _int64(value: int) -> int:
    return value - (1 << 64) if value >= 1 << 63 else value


def _tensor(data: memoryview, top_level: bool) -> TensorInfo:
    info = TensorInfo("", [], 0, False, top_level)
    for number, wire, value in _fields(data):
        if number == 1 and wire == 0:
            info.dims.append(_int64(value))
        elif number == 1 and wire == 2:  # packed dims
            pos = 0
            while pos < len(value):
                dim, pos = _varint(value, pos)
                info.dims.append(_int64(dim))
        elif number == 2 and wire == 0:
            info.data_type = value
        elif number == 8 and wire == 2:
            info.name = bytes(value).decode("utf-8", "replace")
        elif number == 14 and wire == 0:
            info.external = value == 1
    return info


def _sub_messages(data: memoryview, wanted: dict[int, str]) -> Iterator[tuple[str, memoryview]]:
    for number, wire, value in _fields(data):
        if wire == 2 and number in wanted:
            yield wanted[number], value


def _walk(kind: str, data: memoryview, top_level: bool = False, depth: int = 0) -> Iterator[TensorInfo]:
    """Every TensorProto reachable from a message of `kind` (model, function, graph, node, attribute, sparse)
    `depth` messages below the model; ValueError past MAX_MESSAGE_DEPTH."""
    if depth > MAX_MESSAGE_DEPTH:
        raise ValueError(f"its messages nest more than {MAX_MESSAGE_DEPTH} deep (subgraphs within subgraphs)")
    children = {"model": {7: "graph", 25: "function"}, "function": {7: "node"},
                "graph": {1: "node", 5: "tensor", 15: "sparse"}, "node": {5: "attribute"},
                "attribute": {5: "tensor", 6: "subgraph", 10: "tensor", 11: "subgraph", 22: "sparse", 23: "sparse"},
                "sparse": {1: "tensor", 2: "tensor"}}[kind]
    for child, value in _sub_messages(data, children):
        if child == "tensor":
            yield _tensor(value, top_level and kind == "graph")
        else:
            yield from _walk("graph" if child == "subgraph" else child, value, top_level=kind == "model",
                             depth=depth + 1)


def model_tensors(onnx_bytes: bytes | memoryview) -> Iterator[TensorInfo]:
    """Every TensorProto of a serialized ModelProto (ValueError or IndexError if it is not valid protobuf)."""
    return _walk("model", memoryview(onnx_bytes))


__all__ = ["MAX_MESSAGE_DEPTH", "TensorInfo", "model_tensors"]
