"""Window reads as Slices: a traced `buffer.index_select(dim, start + arange(n))` (a window of a streaming graph's
state at a data-dependent start) becomes `Slice(buffer, start, start + n)` in the exported graph.

Why by hand, after the export: torch.export cannot trace a slice at a tensor start without unbacked sizes, so the
torch module reads its windows with index_select, which exports as a Gather. onnxruntime's Gather copies one block
of the inner axes per index: along the last axis, one float at a time. The Slice copies each window as contiguous
runs; the two give the same values (docs/live.md, "The speaker's own translator"). A Gather whose indices are not
such a window, or whose start's shape is not known to be one value, is left as it is.
"""

from __future__ import annotations

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper


def _attribute(node: onnx.NodeProto, name: str):
    for attribute in node.attribute:
        if attribute.name == name:
            return helper.get_attribute_value(attribute)
    return None


class _Values:
    """What the graph's values are, where that can be read without running it: constants and static shapes."""

    def __init__(self, model: onnx.ModelProto) -> None:
        graph = model.graph
        self.producer = {output: node for node in graph.node for output in node.output}
        self.initial = {tensor.name: tensor for tensor in graph.initializer}
        inferred = onnx.shape_inference.infer_shapes(model)
        self.shapes: dict[str, tuple | None] = {}
        for info in [*inferred.graph.value_info, *inferred.graph.input, *inferred.graph.output]:
            dims = info.type.tensor_type.shape.dim
            known = info.type.tensor_type.HasField("shape") and all(d.HasField("dim_value") for d in dims)
            self.shapes[info.name] = tuple(d.dim_value for d in dims) if known else None

    def constant(self, name: str) -> np.ndarray | None:
        """The value of `name` if it is an initializer, a Constant, or a Cast (or CastLike) of one; else None."""
        if name in self.initial:
            return numpy_helper.to_array(self.initial[name])
        node = self.producer.get(name)
        if node is None:
            return None
        if node.op_type == "Constant":
            for key in ("value", "value_ints", "value_int"):
                value = _attribute(node, key)
                if value is not None:
                    return numpy_helper.to_array(value) if key == "value" else np.asarray(value, dtype=np.int64)
            return None
        if node.op_type == "Cast":
            value = self.constant(node.input[0])
            if value is None:
                return None
            return value.astype(helper.tensor_dtype_to_np_dtype(_attribute(node, "to")))
        if node.op_type == "CastLike":
            value, like = self.constant(node.input[0]), self.constant(node.input[1])
            return None if value is None or like is None else value.astype(like.dtype)
        return None

    def index_source(self, name: str) -> onnx.NodeProto | None:
        """The node that made the indices `name`, past Casts to int64 and Reshapes to one axis."""
        node = self.producer.get(name)
        while node is not None:
            if node.op_type == "Cast" and _attribute(node, "to") == TensorProto.INT64:
                pass
            elif node.op_type == "Reshape" and _as_list(self.constant(node.input[1])) == [-1]:
                pass
            else:
                return node
            node = self.producer.get(node.input[0])
        return None

    def window(self, indices: str) -> tuple[str, int, int] | None:
        """(start value, first offset, length) where `indices` is start + range(first, first + length) with start
        one value; else None."""
        add = self.index_source(indices)
        if add is None or add.op_type != "Add":
            return None
        for start, ranged in (add.input, reversed(add.input)):
            made = self.producer.get(ranged)
            if made is None or made.op_type != "Range":
                continue
            bounds = [self.constant(name) for name in made.input]
            if any(bound is None or bound.size != 1 for bound in bounds):
                continue
            first, limit, delta = (int(bound.reshape(())) for bound in bounds)
            shape = self.shapes.get(start)
            if delta == 1 and limit > first and shape is not None and int(np.prod(shape)) == 1 and len(shape) <= 1:
                return start, first, limit - first
        return None


def window_gathers_to_slices(model: onnx.ModelProto) -> int:
    """Rewrite, in place, every Gather of a window at a computed start as a Slice (module docstring); returns how
    many. Nodes left unused are removed."""
    values = _Values(model)
    graph = model.graph
    nodes, rewritten = [], 0
    for node in graph.node:
        window = values.window(node.input[1]) if node.op_type == "Gather" else None
        if window is None:
            nodes.append(node)
            continue
        start, first, length = window
        axis = int(_attribute(node, "axis") or 0)
        stem = f"{node.name or node.output[0]}_window"
        constants = {f"{stem}_shape": [1], f"{stem}_first": [first], f"{stem}_length": [length], f"{stem}_axis": [axis]}
        graph.initializer.extend(numpy_helper.from_array(np.asarray(value, dtype=np.int64), name)
                                 for name, value in constants.items())
        nodes += [
            helper.make_node("Reshape", [start, f"{stem}_shape"], [f"{stem}_start1"], name=f"{stem}_reshape"),
            helper.make_node("Cast", [f"{stem}_start1"], [f"{stem}_start64"], name=f"{stem}_cast",
                             to=TensorProto.INT64),
            helper.make_node("Add", [f"{stem}_start64", f"{stem}_first"], [f"{stem}_begin"], name=f"{stem}_begin"),
            helper.make_node("Add", [f"{stem}_begin", f"{stem}_length"], [f"{stem}_end"], name=f"{stem}_end"),
            helper.make_node("Slice", [node.input[0], f"{stem}_begin", f"{stem}_end", f"{stem}_axis"],
                             list(node.output), name=f"{stem}_slice"),
        ]
        rewritten += 1
    if rewritten:
        del graph.node[:]
        graph.node.extend(_used(nodes, {output.name for output in graph.output}))
        _drop_unused_initializers(graph)
    return rewritten


def _used(nodes: list[onnx.NodeProto], outputs: set[str]) -> list[onnx.NodeProto]:
    """`nodes` less those none of whose outputs is read by a kept node or is a graph output."""
    kept, needed = [], set(outputs)
    for node in reversed(nodes):
        if any(output in needed for output in node.output):
            kept.append(node)
            needed.update(node.input)
    return kept[::-1]


def _drop_unused_initializers(graph: onnx.GraphProto) -> None:
    read = {name for node in graph.node for name in node.input}
    kept = [tensor for tensor in graph.initializer if tensor.name in read]
    del graph.initializer[:]
    graph.initializer.extend(kept)


def _as_list(value: np.ndarray | None) -> list | None:
    return None if value is None else value.reshape(-1).tolist()


__all__ = ["window_gathers_to_slices"]
