"""Graph execution behind one small interface: onnxruntime (the default, runtime/onnxruntime_backend.py) or MNN
(runtime/mnn_backend.py), picked by name."""

from __future__ import annotations

from typing import Protocol

import numpy as np

from gaussiantalker.sdk.bundle import Bundle

from .mnn_backend import MnnBackend
from .onnxruntime_backend import OnnxRuntimeBackend

GRAPH_BACKENDS = ("onnxruntime", "mnn")


class GraphBackend(Protocol):
    """What the runtime needs from a graph executor."""

    def run(self, graph: str, inputs: dict[str, np.ndarray]) -> dict[str, np.ndarray]: ...


def open_backend(bundle: Bundle, backend: str = "onnxruntime", threads: int | None = None) -> GraphBackend:
    """The bundle's graphs ready to run on `backend` ("onnxruntime" or "mnn"), every entry read and checked."""
    if backend == "onnxruntime":
        return OnnxRuntimeBackend(bundle, threads=threads)
    if backend == "mnn":  # MNN itself (an optional extra) is imported only here, by MnnBackend
        return MnnBackend(bundle, threads=threads)
    raise ValueError(f"unknown graph backend {backend!r} (known: {', '.join(GRAPH_BACKENDS)})")


__all__ = ["GRAPH_BACKENDS", "GraphBackend", "open_backend"]
