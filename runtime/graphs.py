"""Graph execution behind a small backend interface: onnxruntime (the default) or MNN (runtime/mnn_backend.py).

A bundle's graphs hold no weights: each weight is a bundle buffer (decoded by its codec) handed to
onnxruntime as an external initializer, so ORT still constant-folds and pre-packs it like an inline weight.

Before onnxruntime sees a graph, every graph and buffer is read and checksummed, and the graph's own protobuf
is read (a minimal wire-format walk: the runtime does not depend on the `onnx` package) to check that each
initializer the manifest feeds exists with the buffer's dtype and shape, and that no tensor points at
external data the bundle does not supply (onnxruntime would otherwise go looking for files on disk).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from gaussiantalker.sdk.bundle import Bundle
from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.codecs import ONNX_DTYPES, ORT_DTYPES
from gaussiantalker.sdk.config import SpeakerConfig
from gaussiantalker.sdk.errors import BundleError, CameraError

# What a speaker bundle (one whose manifest has a 'speaker' section) must hold for TalkingHead.
SPEAKER_GRAPHS = ("translator", "deform")
POSE_TRACK_WIDTH = 6


GRAPH_BACKENDS = ("onnxruntime", "mnn")


class GraphBackend(Protocol):
    """What the runtime needs from a graph executor."""

    def run(self, graph: str, inputs: dict[str, np.ndarray]) -> dict[str, np.ndarray]: ...


def open_backend(bundle: Bundle, backend: str = "onnxruntime", threads: int | None = None) -> GraphBackend:
    """The bundle's graphs ready to run on `backend` ("onnxruntime" or "mnn"), every entry read and checked."""
    if backend == "onnxruntime":
        return OnnxRuntimeBackend(bundle, threads=threads)
    if backend == "mnn":
        from .mnn_backend import MnnBackend  # noqa: PLC0415 - MNN is an optional extra

        return MnnBackend(bundle, threads=threads)
    raise ValueError(f"unknown graph backend {backend!r} (known: {', '.join(GRAPH_BACKENDS)})")


@dataclass
class _LoadedGraph:
    """A graph's checksummed bytes and its decoded external initializers, ready for a session."""

    onnx_bytes: bytes
    initializers: dict[str, np.ndarray]


class OnnxRuntimeBackend:
    """Runs a bundle's ONNX graphs with onnxruntime on the CPU."""

    def __init__(self, bundle: Bundle, threads: int | None = None) -> None:
        import onnxruntime as ort

        self._ort = ort
        self.bundle = bundle
        self.threads = threads
        speaker = "speaker" in bundle.manifest
        if speaker:
            check_speaker_bundle(bundle)
        # Everything is read and checked before the first session is built: damage anywhere fails fast.
        loaded = {name: _load_graph(bundle, name) for name in bundle.graph_names()}
        self.sessions = {name: self._open(bundle, name, graph) for name, graph in loaded.items()}
        if speaker:  # after _check_signature: the declared shapes are now known to be the graphs' own
            check_expression_width(bundle)

    def _open(self, bundle: Bundle, name: str, graph: _LoadedGraph):
        options = self._ort.SessionOptions()
        options.log_severity_level = 3
        # Spinning worker threads cost ~35 ms per deformation call on 2 cores and starve llvmpipe's own
        # rasterizer threads, so idle ORT threads sleep instead.
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        if self.threads:
            options.intra_op_num_threads = int(self.threads)
        if graph.initializers:
            values = [self._ort.OrtValue.ortvalue_from_numpy(array) for array in graph.initializers.values()]
            options.add_external_initializers(list(graph.initializers), values)
        try:
            session = self._ort.InferenceSession(graph.onnx_bytes, options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own untyped errors
            raise BundleError(f"{bundle.path}: graph {name!r} cannot be loaded by onnxruntime: {exc}") from exc
        _check_signature(bundle, name, bundle.graph_info(name), session)
        return session

    def run(self, graph: str, inputs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        session = self.sessions.get(graph)
        if session is None:
            raise BundleError(f"{self.bundle.path}: bundle has no graph {graph!r} (it holds: "
                              f"{', '.join(sorted(self.sessions)) or 'no graphs'})")
        names = [o.name for o in session.get_outputs()]
        return dict(zip(names, session.run(names, inputs), strict=True))


def check_speaker_bundle(bundle: Bundle) -> None:
    """A speaker bundle must hold both graphs (a flame-driven scene's only `deform`), a valid camera, and (if any)
    a float32 [T, 6] pose track."""
    scene = bundle.manifest.get("scene")
    flame_driven = isinstance(scene, dict) and isinstance(scene.get("drive"), dict) and \
        scene["drive"].get("driver") == "flame"
    required = [name for name in SPEAKER_GRAPHS if not (flame_driven and name == "translator")]
    missing = [name for name in required if name not in bundle.manifest["graphs"]]
    if missing:
        raise BundleError(f"{bundle.path}: speaker bundle lacks the {' and '.join(map(repr, missing))} graph"
                          f"{'s' if len(missing) > 1 else ''} (it holds: {', '.join(bundle.graph_names()) or 'none'})")
    for section in ("speaker", "camera"):
        if not isinstance(bundle.manifest[section], dict):
            raise BundleError(f"{bundle.path}: manifest {section!r} section is not a table")
    try:
        Camera.from_dict(bundle.manifest["camera"])
    except CameraError as exc:
        raise BundleError(f"{bundle.path}: manifest 'camera' section is invalid: {exc}") from None
    if bundle.has_buffer("pose_track"):
        entry = bundle.manifest["buffers"]["pose_track"]
        shape = entry["shape"]
        if entry["dtype"] != "float32" or len(shape) != 2 or shape[0] < 1 or shape[1] != POSE_TRACK_WIDTH:
            raise BundleError(f"{bundle.path}: buffer 'pose_track' is {entry['dtype']} {shape}, expected float32 "
                              f"[T >= 1, {POSE_TRACK_WIDTH}] (rotation, translation per frame)")


def check_expression_width(bundle: Bundle) -> None:
    """The speaker config's n_expr must be the graphs' expression width (drives are built from it); each backend
    calls this once its graphs' signatures are known to be the manifest's."""
    n_expr = bundle.manifest["speaker"].get("n_expr", SpeakerConfig.n_expr)
    for graph, kind in (("deform", "inputs"), ("translator", "outputs")):
        if graph not in bundle.manifest["graphs"]:
            continue
        for value in bundle.graph_info(graph)[kind]:
            width = value["shape"][-1] if value["shape"] else None
            if value["name"] == "expression" and isinstance(width, int) and width != n_expr:
                raise BundleError(f"{bundle.path}: manifest speaker n_expr is {n_expr!r} but graph {graph!r} "
                                  f"{kind[:-1]} 'expression' has {width} coefficients")


def _load_graph(bundle: Bundle, name: str) -> _LoadedGraph:
    """Read and checksum a graph and its buffers; check its initializers against the manifest first."""
    onnx_bytes = bundle.graph_bytes(name)
    feeds = bundle.graph_info(name).get("initializers", {})
    _check_initializers(bundle, name, onnx_bytes, feeds)
    arrays = {init: np.ascontiguousarray(bundle.buffer(buffer)) for init, buffer in feeds.items()}
    return _LoadedGraph(onnx_bytes, arrays)


def _check_initializers(bundle: Bundle, name: str, onnx_bytes: bytes, feeds: dict[str, str]) -> None:
    """Each fed initializer exists with the buffer's dtype and shape; nothing else wants external data."""
    try:
        tensors = list(_model_tensors(memoryview(onnx_bytes)))
    except (ValueError, IndexError) as exc:
        raise BundleError(f"{bundle.path}: graph {name!r} is not a valid ONNX model ({exc})") from None
    top_level = {t.name: t for t in tensors if t.top_level}
    for tensor in tensors:
        if tensor.external and not (tensor.top_level and tensor.name in feeds):
            raise BundleError(f"{bundle.path}: graph {name!r} tensor {tensor.name!r} wants external data the "
                              f"bundle does not supply (refused: the runtime reads nothing outside the bundle)")
    for init, buffer in feeds.items():
        tensor = top_level.get(init)
        if tensor is None:
            raise BundleError(f"{bundle.path}: graph {name!r} has no initializer {init!r} (the manifest feeds it "
                              f"from buffer {buffer!r})")
        entry = bundle.manifest["buffers"][buffer]
        dtype = ONNX_DTYPES.get(tensor.data_type, f"ONNX type {tensor.data_type}")
        if dtype != entry["dtype"] or tensor.dims != list(entry["shape"]):
            raise BundleError(f"{bundle.path}: graph {name!r} initializer {init!r} is {dtype} {tensor.dims} but "
                              f"buffer {buffer!r} is {entry['dtype']} {entry['shape']}")


def _check_signature(bundle: Bundle, name: str, info: dict, session) -> None:
    """The manifest's input/output names, ranks, fixed sizes and dtypes must be what the graph really has."""
    for kind, declared, actual in (("input", info["inputs"], session.get_inputs()),
                                   ("output", info["outputs"], session.get_outputs())):
        actual_by_name = {a.name: a for a in actual}
        if sorted(d["name"] for d in declared) != sorted(actual_by_name):
            raise BundleError(f"{bundle.path}: graph {name!r} {kind}s are {sorted(actual_by_name)} but the "
                              f"manifest declares {sorted(d['name'] for d in declared)}")
        for d in declared:
            a = actual_by_name[d["name"]]
            fixed_differ = len(a.shape) == len(d["shape"]) and any(
                isinstance(x, int) and isinstance(y, int) and x != y for x, y in zip(a.shape, d["shape"], strict=True))
            if ORT_DTYPES.get(a.type) != d["dtype"] or len(a.shape) != len(d["shape"]) or fixed_differ:
                raise BundleError(f"{bundle.path}: graph {name!r} {kind} {d['name']!r} is {a.type} {a.shape} but "
                                  f"the manifest declares {d['dtype']} {d['shape']}")


# -- minimal ONNX protobuf walk ---------------------------------------------------------------------------------
# Field numbers from onnx.proto: ModelProto.graph 7, .functions 25; FunctionProto.node 7; GraphProto.node 1,
# .initializer 5, .sparse_initializer 15; NodeProto.attribute 5; AttributeProto.t 5, .g 6, .tensors 10,
# .graphs 11, .sparse_tensor 22, .sparse_tensors 23; SparseTensorProto.values 1, .indices 2;
# TensorProto.dims 1, .data_type 2, .name 8, .data_location 14 (1 = EXTERNAL).


@dataclass
class _TensorInfo:
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


def _tensor(data: memoryview, top_level: bool) -> _TensorInfo:
    info = _TensorInfo("", [], 0, False, top_level)
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


def _walk(kind: str, data: memoryview, top_level: bool = False) -> Iterator[_TensorInfo]:
    """Every TensorProto reachable from a message of `kind` (model, function, graph, node, attribute, sparse)."""
    children = {"model": {7: "graph", 25: "function"}, "function": {7: "node"},
                "graph": {1: "node", 5: "tensor", 15: "sparse"}, "node": {5: "attribute"},
                "attribute": {5: "tensor", 6: "subgraph", 10: "tensor", 11: "subgraph", 22: "sparse", 23: "sparse"},
                "sparse": {1: "tensor", 2: "tensor"}}[kind]
    for child, value in _sub_messages(data, children):
        if child == "tensor":
            yield _tensor(value, top_level and kind == "graph")
        else:
            yield from _walk("graph" if child == "subgraph" else child, value, top_level=kind == "model")


def _model_tensors(onnx_bytes: memoryview) -> Iterator[_TensorInfo]:
    return _walk("model", onnx_bytes)
