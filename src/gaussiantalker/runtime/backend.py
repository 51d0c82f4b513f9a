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


def check_backend_name(name: str) -> str:
    """`name` itself if it is a graph backend, else ValueError listing them."""
    if name not in GRAPH_BACKENDS:
        raise ValueError(f"unknown graph backend {name!r} (known: {', '.join(GRAPH_BACKENDS)})")
    return name


def open_backend(bundle: Bundle, backend: str = "onnxruntime", threads: int | None = None) -> GraphBackend:
    """The bundle's graphs ready to run on `backend` ("onnxruntime" or "mnn"), every entry read and checked."""
    if check_backend_name(backend) == "onnxruntime":
        return OnnxRuntimeBackend(bundle, threads=threads)
    return MnnBackend(bundle, threads=threads)  # MNN itself (an optional extra) is imported only by MnnBackend


__all__ = ["GRAPH_BACKENDS", "GraphBackend", "check_backend_name", "open_backend"]
