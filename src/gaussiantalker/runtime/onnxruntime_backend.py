"""The default graph backend: a bundle's ONNX graphs run with onnxruntime on the CPU.

A bundle's graphs hold no weights: each weight is a bundle buffer (decoded by its codec) handed to onnxruntime as
an external initializer, so ORT still constant-folds and pre-packs it like an inline weight. Before onnxruntime
sees a graph, every graph and buffer is read and checksummed and checked against the manifest
(runtime/bundle_checks.py): onnxruntime would otherwise go looking on disk for external data the bundle does not
supply. A graph only live sessions run (the streaming translator) is checked with the rest but gets its session on
first use.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from gaussiantalker.sdk.bundle import STREAM_GRAPHS, Bundle
from gaussiantalker.sdk.errors import BundleError

from .bundle_checks import (
    check_expression_width,
    check_initializers,
    check_signature,
    check_speaker_bundle,
    is_speaker_bundle,
)

# The most of onnxruntime's reason a BundleError quotes (its messages carry C++ signatures and may span lines; a
# refusal is one line, docs/untrusted-input.md).
MAX_REASON_CHARS = 400
# Graphs only some uses run (a live session streams; offline rendering never does): read and checked with the
# others, their session opened on first use (the demo speaker's stream: 90 ms of a 430 ms open).
ON_FIRST_USE = tuple(name for graphs in STREAM_GRAPHS for name in graphs)


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
        speaker = is_speaker_bundle(bundle)
        if speaker:
            check_speaker_bundle(bundle)
        # Everything is read and checked before the first session is built: damage anywhere fails fast.
        loaded = {name: _load_graph(bundle, name) for name in bundle.graph_names()}
        self._waiting = {name: graph for name, graph in loaded.items() if name in ON_FIRST_USE}
        self._opening = threading.Lock()  # a live server's pool threads may ask for one at once
        self.sessions = {name: self._open(bundle, name, graph) for name, graph in loaded.items()
                         if name not in ON_FIRST_USE}
        if speaker:  # after check_signature: the declared shapes are now known to be the graphs' own
            check_expression_width(bundle)

    def _open(self, bundle: Bundle, name: str, graph: _LoadedGraph):
        options = self._ort.SessionOptions()
        options.log_severity_level = 3
        # Spinning worker threads cost time on every deformation call and starve llvmpipe's own rasterizer
        # threads (measured: docs/speed.md), so idle ORT threads sleep instead.
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        if self.threads:
            options.intra_op_num_threads = int(self.threads)
        if graph.initializers:
            values = [self._ort.OrtValue.ortvalue_from_numpy(array) for array in graph.initializers.values()]
            options.add_external_initializers(list(graph.initializers), values)
        try:
            session = self._ort.InferenceSession(graph.onnx_bytes, options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own untyped errors
            raise BundleError(f"{bundle.path}: graph {name!r} cannot be loaded by onnxruntime: "
                              f"{_one_line(str(exc))}") from exc
        check_signature(bundle, name, bundle.graph_info(name), session)
        return session

    def run(self, graph: str, inputs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Run `graph` on `inputs` (name -> array); every output by name."""
        session = self.sessions.get(graph)
        if session is None and graph in self._waiting:
            with self._opening:
                if graph in self._waiting:
                    self.sessions[graph] = self._open(self.bundle, graph, self._waiting[graph])
                    del self._waiting[graph]
            session = self.sessions[graph]
        if session is None:
            raise BundleError(f"{self.bundle.path}: bundle has no graph {graph!r} (it holds: "
                              f"{', '.join(sorted(self.bundle.graph_names())) or 'no graphs'})")
        names = [o.name for o in session.get_outputs()]
        return dict(zip(names, session.run(names, inputs), strict=True))


def _one_line(text: str, limit: int = MAX_REASON_CHARS) -> str:
    """onnxruntime's reason on one line (whitespace collapsed), at most `limit` characters: its start and its end,
    where the cause is named after the C++ location it was raised at."""
    text = " ".join(text.split())
    if len(text) <= limit:
        return text
    head = limit // 3
    return f"{text[:head]} ... {text[len(text) - (limit - head - 5):]}"


def _load_graph(bundle: Bundle, name: str) -> _LoadedGraph:
    """Read and checksum a graph and its buffers; check its initializers against the manifest first."""
    onnx_bytes = bundle.graph_bytes(name)
    feeds = bundle.graph_info(name).get("initializers", {})
    check_initializers(bundle, name, onnx_bytes, feeds)
    arrays = {init: np.ascontiguousarray(bundle.buffer(buffer)) for init, buffer in feeds.items()}
    return _LoadedGraph(onnx_bytes, arrays)


__all__ = ["OnnxRuntimeBackend"]
