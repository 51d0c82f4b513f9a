"""Bundle graphs -> MNN graphs stored beside them (`gt-export --mnn`, docs/mnn.md).

Each graph is rebuilt with its weights inline as a reader decodes them (so MNN computes what onnxruntime
computes), constant-folded by onnxruntime's basic optimisation level (the graph onnxruntime itself runs; MNN's
converter crashes on some unfolded shape arithmetic), rewritten where MNN's kernels differ from the ONNX
definition (`mnn_compatible`), then converted by MNN in a guarded child process (exporter/export/mnn_worker.py).
"""

from __future__ import annotations

import importlib.metadata
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import onnx
from onnx import helper, numpy_helper

from gaussiantalker.runtime.mnn_backend import INSTALL_HINT
from gaussiantalker.sdk.bundle import BundleWriter
from gaussiantalker.sdk.errors import BundleError

from .mnn_worker import REPORT_PREFIX

MNN_ENTRY_PREFIX = "mnn/"
CONVERT_TIMEOUT_S = 900


def mnn_version() -> str:
    """The installed MNN's version (read from its package metadata: importing MNN prints to stdout)."""
    try:
        return importlib.metadata.version("MNN")
    except importlib.metadata.PackageNotFoundError:
        raise BundleError(f"--mnn needs MNN's converter, which is not installed; install it with: {INSTALL_HINT}"
                          ) from None


def graph_with_weights(writer: BundleWriter, name: str) -> onnx.ModelProto:
    """Graph `name` of `writer` with every external initializer replaced by its decoded buffer."""
    model = onnx.ModelProto.FromString(writer.graph_onnx(name))
    feeds = writer.graph_info(name)["initializers"]
    for tensor in model.graph.initializer:
        if tensor.name in feeds:
            array = np.ascontiguousarray(writer.decoded_buffer(feeds[tensor.name]))
            tensor.CopyFrom(numpy_helper.from_array(array, tensor.name))
    return model


def fold_constants(model: onnx.ModelProto) -> onnx.ModelProto:
    """The model after onnxruntime's basic optimisations (constant folding, no fusions into its own operators)."""
    import onnxruntime as ort  # noqa: PLC0415

    with tempfile.TemporaryDirectory(prefix="gt-mnn-") as folder:
        options = ort.SessionOptions()
        options.log_severity_level = 3
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_BASIC
        options.optimized_model_filepath = os.path.join(folder, "folded.onnx")
        ort.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"])
        return onnx.load(options.optimized_model_filepath)


def _erf_gelu(node: onnx.NodeProto, prefix: str) -> tuple[list[onnx.NodeProto], list[onnx.TensorProto]]:
    """Gelu(x) as 0.5 x (1 + erf(x / sqrt 2)), its ONNX definition: MNN 3.6's Gelu kernel is an approximation
    (measured off on the translator's activations: docs/mnn.md), its Erf is exact to float32."""
    x, y = node.input[0], node.output[0]
    constants = [numpy_helper.from_array(np.array(v, np.float32), f"{prefix}_{n}")
                 for n, v in (("rsqrt2", 1 / np.sqrt(2)), ("one", 1.0), ("half", 0.5))]
    nodes = [helper.make_node("Mul", [x, f"{prefix}_rsqrt2"], [f"{prefix}_scaled"]),
             helper.make_node("Erf", [f"{prefix}_scaled"], [f"{prefix}_erf"]),
             helper.make_node("Add", [f"{prefix}_erf", f"{prefix}_one"], [f"{prefix}_gate"]),
             helper.make_node("Mul", [x, f"{prefix}_half"], [f"{prefix}_halfx"]),
             helper.make_node("Mul", [f"{prefix}_halfx", f"{prefix}_gate"], [y])]
    return nodes, constants


def _summed_l2(node: onnx.NodeProto, prefix: str) -> tuple[list[onnx.NodeProto], list[onnx.TensorProto]]:
    """ReduceL2(x, axes) as sqrt(ReduceSum(x * x, axes)): MNN 3.6 ignores ReduceL2's `axes` input (opset 18)
    and reduces every axis; its ReduceSum reads the input."""
    attributes = {a.name: helper.get_attribute_value(a) for a in node.attribute}
    nodes = [helper.make_node("Mul", [node.input[0], node.input[0]], [f"{prefix}_square"]),
             helper.make_node("ReduceSum", [f"{prefix}_square", *node.input[1:]], [f"{prefix}_sum"], **attributes),
             helper.make_node("Sqrt", [f"{prefix}_sum"], [node.output[0]])]
    return nodes, []


# Operators MNN 3.6's converter or kernels get wrong, each rewritten to what the ONNX specification defines.
_REWRITES = {"Gelu": _erf_gelu, "ReduceL2": _summed_l2}


def mnn_compatible(model: onnx.ModelProto) -> onnx.ModelProto:
    """A copy of `model` with `_REWRITES` applied: the same function (onnxruntime gives identical outputs for
    both), in operators MNN computes as ONNX defines them."""
    model = onnx.ModelProto.FromString(model.SerializeToString())
    nodes: list[onnx.NodeProto] = []
    for index, node in enumerate(model.graph.node):
        rewrite = _REWRITES.get(node.op_type) if node.domain in ("", "ai.onnx") else None
        if rewrite is None:
            nodes.append(node)
            continue
        replacement, constants = rewrite(node, f"mnn_{index}_{node.op_type.lower()}")
        nodes.extend(replacement)
        model.graph.initializer.extend(constants)
    del model.graph.node[:]
    model.graph.node.extend(nodes)
    onnx.checker.check_model(model)
    return model


def convert_to_mnn(model: onnx.ModelProto, graph: str) -> bytes:
    """MNN's converter on `model`, in a child process that may not open sockets or start processes."""
    with tempfile.TemporaryDirectory(prefix="gt-mnn-") as folder:
        source, target = Path(folder, f"{graph}.onnx"), Path(folder, f"{graph}.mnn")
        onnx.save(model, source)
        environment = {**os.environ, "PIP_NO_INDEX": "1", "PIP_NO_INPUT": "1"}
        try:
            run = subprocess.run([sys.executable, "-m", "gaussiantalker.exporter.export.mnn_worker", str(source),
                                  str(target)], capture_output=True, text=True, timeout=CONVERT_TIMEOUT_S,
                                 env=environment, check=False)
        except subprocess.TimeoutExpired:
            raise BundleError(f"MNN's converter did not finish graph {graph!r} in {CONVERT_TIMEOUT_S} s") from None
        log = (run.stdout + run.stderr).strip()
        report = next((json.loads(line[len(REPORT_PREFIX):]) for line in log.splitlines()
                       if line.startswith(REPORT_PREFIX)), None)
        tail = "\n".join(line for line in log.splitlines()[-12:] if not line.startswith(REPORT_PREFIX))
        if run.returncode < 0:
            raise BundleError(f"MNN's converter crashed (signal {-run.returncode}) on graph {graph!r}; its last "
                              f"output:\n{tail}")
        if report is None:
            raise BundleError(f"MNN's converter on graph {graph!r} exited ({run.returncode}) without a report:\n"
                              f"{tail}")
        if report["blocked"]:
            raise BundleError(f"MNN's converter tried {', '.join(report['blocked'])} while converting graph "
                              f"{graph!r}; refused (an export never goes online or installs anything)")
        if not report["converted"] or not target.is_file():
            reason = f" ({report['error']})" if report.get("error") else ""
            raise BundleError(f"MNN's converter cannot convert graph {graph!r}{reason}:\n{tail}")
        return target.read_bytes()


def mnn_graph(writer: BundleWriter, name: str) -> bytes:
    """The `.mnn` model of `writer`'s graph `name`."""
    return convert_to_mnn(mnn_compatible(fold_constants(graph_with_weights(writer, name))), name)


def add_mnn_graphs(writer: BundleWriter) -> dict[str, int]:
    """Convert every graph already in `writer` and store each `.mnn` model as entry `mnn/<graph>` plus the
    manifest's `mnn` section; returns each model's bytes."""
    version = mnn_version()
    section: dict = {"converter": f"MNN {version}", "graphs": {}}
    sizes = {}
    for name in writer.graph_names():
        model = mnn_graph(writer, name)
        entry = MNN_ENTRY_PREFIX + name
        writer.add_buffer(entry, np.frombuffer(model, dtype=np.uint8))
        info = writer.graph_info(name)
        section["graphs"][name] = {"buffer": entry, "inputs": info["inputs"], "outputs": info["outputs"]}
        sizes[name] = len(model)
    writer.metadata["mnn"] = section
    return sizes
