"""Graph execution behind a small backend interface; onnxruntime is the one backend today (MNN may follow).

A bundle's graphs hold no weights: each weight is a bundle buffer (decoded by its codec) handed to
onnxruntime as an external initializer, so ORT still constant-folds and pre-packs it like an inline weight.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from gaussiantalker.sdk.bundle import Bundle
from gaussiantalker.sdk.errors import BundleError

_ORT_TYPES = {"tensor(float)": "float32", "tensor(float16)": "float16", "tensor(int64)": "int64",
              "tensor(int32)": "int32", "tensor(uint8)": "uint8"}


class GraphBackend(Protocol):
    """What the runtime needs from a graph executor."""

    def run(self, graph: str, inputs: dict[str, np.ndarray]) -> dict[str, np.ndarray]: ...


class OnnxRuntimeBackend:
    """Runs a bundle's ONNX graphs with onnxruntime on the CPU."""

    def __init__(self, bundle: Bundle, threads: int | None = None) -> None:
        import onnxruntime as ort

        self._ort = ort
        self.threads = threads
        self.sessions = {}
        for name in bundle.graph_names():
            self.sessions[name] = self._open(bundle, name)

    def _open(self, bundle: Bundle, name: str):
        info = bundle.graph_info(name)
        options = self._ort.SessionOptions()
        options.log_severity_level = 3
        # Spinning worker threads cost ~35 ms per deformation call on 2 cores and starve llvmpipe's own
        # rasterizer threads, so idle ORT threads sleep instead.
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        if self.threads:
            options.intra_op_num_threads = int(self.threads)
        initializers = info.get("initializers", {})
        if initializers:
            values = [self._ort.OrtValue.ortvalue_from_numpy(np.ascontiguousarray(bundle.buffer(buf)))
                      for buf in initializers.values()]
            options.add_external_initializers(list(initializers), values)
        try:
            session = self._ort.InferenceSession(bundle.graph_bytes(name), options,
                                                 providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own untyped errors
            raise BundleError(f"{bundle.path}: graph {name!r} cannot be loaded by onnxruntime: {exc}") from exc
        _check_signature(bundle, name, info, session)
        return session

    def run(self, graph: str, inputs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        session = self.sessions[graph]
        names = [o.name for o in session.get_outputs()]
        return dict(zip(names, session.run(names, inputs), strict=True))


def _check_signature(bundle: Bundle, name: str, info: dict, session) -> None:
    """The manifest's input/output names, ranks and dtypes must be what the graph really has."""
    for kind, declared, actual in (("input", info.get("inputs", []), session.get_inputs()),
                                   ("output", info.get("outputs", []), session.get_outputs())):
        actual_by_name = {a.name: a for a in actual}
        if sorted(d["name"] for d in declared) != sorted(actual_by_name):
            raise BundleError(f"{bundle.path}: graph {name!r} {kind}s are {sorted(actual_by_name)} but the "
                              f"manifest declares {sorted(d['name'] for d in declared)}")
        for d in declared:
            a = actual_by_name[d["name"]]
            if _ORT_TYPES.get(a.type) != d["dtype"] or len(a.shape) != len(d["shape"]):
                raise BundleError(f"{bundle.path}: graph {name!r} {kind} {d['name']!r} is {a.type} rank "
                                  f"{len(a.shape)} but the manifest declares {d['dtype']} {d['shape']}")
