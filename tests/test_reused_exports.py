"""`reused_exports()` (exporter/export/onnx_export.py): inside the block an export equal to an earlier one returns a
copy of its graph without tracing again; any change to what the graph depends on (a weight, a plain attribute, the
example inputs, the names) traces afresh, and outside the block every export traces."""

from __future__ import annotations

import pytest
import torch

from gaussiantalker.exporter.export import onnx_export
from gaussiantalker.exporter.export.onnx_export import export_onnx, reused_exports


class _Scaled(torch.nn.Module):
    """A layer whose graph depends on its weights and on a plain attribute (`power`)."""

    def __init__(self, power: int = 2) -> None:
        super().__init__()
        self.linear = torch.nn.Linear(3, 2)
        self.power = power

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.linear(x) ** self.power


@pytest.fixture
def traces(monkeypatch):
    """The number of real torch.onnx traces made so far ([count])."""
    count = [0]
    traced = onnx_export._traced

    def counting(*args, **kwargs):
        count[0] += 1
        return traced(*args, **kwargs)

    monkeypatch.setattr(onnx_export, "_traced", counting)
    return count


def _export(module: torch.nn.Module, x: torch.Tensor | None = None, names: tuple = ("x", "y")):
    x = torch.ones(1, 3) if x is None else x
    return export_onnx(module, (x,), [names[0]], [names[1]])


def test_an_equal_export_in_the_block_is_the_first_ones_graph(traces):
    torch.manual_seed(0)
    module = _Scaled()
    fresh = _export(module).SerializeToString()
    with reused_exports():
        first = _export(module)
        first.graph.name = "changed by its caller"  # a caller's change to its proto is not kept for the next
        again = _export(module)
        torch.manual_seed(0)
        twin = _export(_Scaled())  # another module object with the same class, attributes and weights
    assert traces[0] == 2  # the fresh one outside the block, the first inside it
    assert again.SerializeToString() == fresh and twin.SerializeToString() == fresh


@pytest.mark.parametrize("change", ["weight", "attribute", "input", "names"])
def test_anything_the_graph_depends_on_traces_again(traces, change):
    torch.manual_seed(0)
    module = _Scaled()
    with reused_exports():
        _export(module)
        if change == "weight":
            with torch.no_grad():
                module.linear.weight[0, 0] += 1e-6
            _export(module)
        elif change == "attribute":
            module.power = 3
            _export(module)
        elif change == "input":
            _export(module, torch.ones(2, 3))
        else:
            _export(module, names=("audio", "y"))
    assert traces[0] == 2


def test_outside_the_block_every_export_traces(traces):
    module = _Scaled()
    _export(module)
    _export(module)
    with reused_exports():
        _export(module)
    _export(module)
    assert traces[0] == 4
