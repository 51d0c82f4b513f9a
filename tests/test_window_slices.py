"""Window reads as Slices (exporter/export/window_slices.py): a traced `index_select(start + arange(n))` becomes a
Slice with the same values (exact: both copy the same floats); other Gathers stay as they are."""

from __future__ import annotations

import numpy as np
import onnx
import onnxruntime as ort
import torch

from gaussiantalker.exporter.export import onnx_export
from gaussiantalker.exporter.export.window_slices import window_gathers_to_slices


class _Windows(torch.nn.Module):
    """Two windows at a start read from `keep`, one Gather of fixed indices, one of indices per start row."""

    def forward(self, buffer: torch.Tensor, keep: torch.Tensor):
        start = keep.reshape(1).to(torch.int64)
        last = buffer.index_select(-1, 2 * start + torch.arange(5))  # a window along the last axis
        middle = buffer.index_select(1, start + torch.arange(1, 3))  # along axis 1, offset by 1
        fixed = buffer.index_select(-1, torch.tensor([0, 2, 4]))  # not a window at a computed start
        starts = torch.stack([start, start + 1])  # two starts: indices [2, 4], not one window
        spread = buffer.index_select(-1, (starts + torch.arange(4)).reshape(-1))
        return last, middle, fixed, spread


def _gathers(model: onnx.ModelProto) -> int:
    return sum(node.op_type == "Gather" for node in model.graph.node)


def test_window_gathers_become_slices_with_the_same_values():
    buffer = torch.randn(2, 6, 16)
    batch = torch.export.Dim("batch", min=1, max=64)
    model = onnx_export.export_onnx(_Windows(), (buffer, torch.tensor([1.0])), ["buffer", "keep"],
                                    ["last", "middle", "fixed", "spread"],
                                    dynamic_shapes={"buffer": {0: batch}, "keep": None})
    before = onnx.ModelProto.FromString(model.SerializeToString())
    gathers = _gathers(model)
    assert window_gathers_to_slices(model) == 2
    onnx.checker.check_model(model)
    assert _gathers(model) == gathers - 2 and sum(node.op_type == "Slice" for node in model.graph.node) >= 2
    assert window_gathers_to_slices(model) == 0  # nothing left to rewrite
    sessions = [ort.InferenceSession(graph.SerializeToString(), providers=["CPUExecutionProvider"])
                for graph in (before, model)]
    rng = np.random.default_rng(0)
    for batch_size, keep in ((1, 0.0), (3, 1.0), (5, 2.0)):
        feed = {"buffer": rng.standard_normal((batch_size, 6, 16)).astype(np.float32),
                "keep": np.array([keep], np.float32)}
        for gathered, sliced in zip(*(session.run(None, feed) for session in sessions), strict=True):
            assert gathered.shape == sliced.shape and np.array_equal(gathered, sliced)
        start = int(keep)
        assert np.array_equal(sessions[1].run(["last"], feed)[0], feed["buffer"][..., 2 * start:2 * start + 5])
