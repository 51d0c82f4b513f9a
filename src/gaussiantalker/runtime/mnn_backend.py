"""Graph execution with MNN (`TalkingHead(..., backend="mnn")`): the bundle's `.mnn` graphs, written by
`gt-export --mnn` beside the ONNX ones (docs/mnn.md), run through MNN's Module API.

MNN is an optional extra (`pip install "gaussiantalker-sdk[mnn]"`). Each `.mnn` graph is a checksummed bundle
entry holding its weights inline; its inputs and outputs are the ONNX graph's, checked at load.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator

import numpy as np

from gaussiantalker.sdk.bundle import Bundle
from gaussiantalker.sdk.errors import BundleError

from .bundle_checks import check_expression_width, check_speaker_bundle, is_speaker_bundle

INSTALL_HINT = 'pip install "gaussiantalker-sdk[mnn]"'


@contextlib.contextmanager
def _stdout_silenced() -> Iterator[None]:
    """Send file descriptor 1 to /dev/null: MNN's native library prints its CPU features there when it is first
    imported, which would corrupt a video an app streams to stdout."""
    try:
        saved = os.dup(1)
    except OSError:  # no stdout at all: nothing to protect
        yield
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def import_mnn():
    """MNN's `nn` and `expr` modules; BundleError saying what to install when the extra is missing."""
    try:
        with _stdout_silenced():
            import MNN.expr as mnn_expr  # noqa: PLC0415 - optional extra, imported on first use
            import MNN.nn as mnn_nn  # noqa: PLC0415
    except ImportError as exc:
        raise BundleError(f'backend="mnn" needs MNN, which is not installed ({exc}); install it with: '
                          f"{INSTALL_HINT}") from None
    return mnn_nn, mnn_expr


def mnn_graph_names(bundle: Bundle) -> list[str]:
    """Names of the graphs the bundle carries as `.mnn` models (empty: it was exported without --mnn)."""
    section = bundle.manifest.get("mnn")
    graphs = section.get("graphs") if isinstance(section, dict) else None
    return sorted(graphs) if isinstance(graphs, dict) else []


class MnnBackend:
    """Runs a bundle's `.mnn` graphs with MNN on the CPU (one thread unless told otherwise)."""

    def __init__(self, bundle: Bundle, threads: int | None = None) -> None:
        self.bundle = bundle
        self.threads = int(threads) if threads else 1
        names = mnn_graph_names(bundle)
        missing = [name for name in bundle.graph_names() if name not in names]
        if missing:
            held = f"MNN graphs only for {', '.join(names)}" if names else "no MNN graphs"
            raise BundleError(f"{bundle.path}: bundle has {held} (missing: {', '.join(missing)}); re-export it with "
                              "`gt-export --mnn` to run it on MNN, or use backend=\"onnxruntime\"")
        if is_speaker_bundle(bundle):
            check_speaker_bundle(bundle)
        self._nn, self._expr = import_mnn()
        # Everything is read and checksummed before the first module is built: damage anywhere fails fast.
        models = {name: self._model_bytes(name) for name in names}
        self.modules = {name: self._open(name, data) for name, data in models.items()}
        if is_speaker_bundle(bundle):  # after _open: the modules' names are now known to be the manifest's
            check_expression_width(bundle)

    def _entry(self, name: str) -> dict:
        entry = self.bundle.manifest["mnn"]["graphs"][name]
        if not isinstance(entry, dict) or not isinstance(entry.get("buffer"), str):
            raise BundleError(f"{self.bundle.path}: manifest 'mnn' graph {name!r} names no buffer")
        return entry

    def _model_bytes(self, name: str) -> bytes:
        buffer = self._entry(name)["buffer"]
        if not self.bundle.has_buffer(buffer):
            raise BundleError(f"{self.bundle.path}: MNN graph {name!r} refers to missing buffer {buffer!r}")
        data = self.bundle.buffer(buffer)  # checksummed here
        if data.dtype != np.uint8 or data.ndim != 1:
            raise BundleError(f"{self.bundle.path}: MNN graph {name!r} buffer {buffer!r} is {data.dtype} "
                              f"{list(data.shape)}, expected uint8 [nbytes]")
        return data.tobytes()

    def _open(self, name: str, model: bytes):
        """One MNN module with the ONNX graph's input and output names (checked against the model's own)."""
        info = self.bundle.graph_info(name)
        inputs = [value["name"] for value in info["inputs"]]
        outputs = [value["name"] for value in info["outputs"]]
        unsupported = [value["name"] for value in info["inputs"] if value.get("dtype") != "float32"]
        if unsupported:
            raise BundleError(f"{self.bundle.path}: MNN graph {name!r} inputs {unsupported} are not float32 (the "
                              "MNN backend feeds float32 only)")
        # MNN's Python API loads a module from a file path only: the checksummed bytes go through a private
        # temporary file, removed as soon as the module is built.
        handle = tempfile.NamedTemporaryFile(suffix=".mnn", delete=False)
        try:
            with handle:
                handle.write(model)
            try:
                with _stdout_silenced():
                    module = self._nn.load_module_from_file(handle.name, inputs, outputs, thread_num=self.threads)
            except Exception as exc:  # MNN raises untyped errors (SystemError) for a model it cannot load
                raise BundleError(f"{self.bundle.path}: MNN graph {name!r} cannot be loaded by MNN: {exc}") from None
        finally:
            os.unlink(handle.name)
        held = module.get_info()
        if list(held.get("inputNames", [])) != inputs or list(held.get("outputNames", [])) != outputs:
            raise BundleError(f"{self.bundle.path}: MNN graph {name!r} has inputs {held.get('inputNames')} and "
                              f"outputs {held.get('outputNames')}; its ONNX graph has {inputs} and {outputs}")
        return module, inputs, outputs

    def run(self, graph: str, inputs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        loaded = self.modules.get(graph)
        if loaded is None:
            raise BundleError(f"{self.bundle.path}: bundle has no graph {graph!r} (it holds: "
                              f"{', '.join(sorted(self.modules)) or 'no graphs'})")
        module, input_names, output_names = loaded
        expr = self._expr
        feeds = []
        for name in input_names:
            array = np.ascontiguousarray(inputs[name], dtype=np.float32)
            feeds.append(expr.const(array, list(array.shape), expr.NCHW))
        results = module.forward(feeds)
        arrays = {}
        for name, value in zip(output_names, results, strict=True):
            if value.data_format == expr.NC4HW4:  # a convolution's packed layout: back to the graph's NCHW
                value = expr.convert(value, expr.NCHW)
            arrays[name] = np.array(value.read(), copy=True)  # the module reuses its output memory next call
        return arrays
