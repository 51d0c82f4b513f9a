"""The inpainting generator F as an ONNX graph (the `inpaint` graph of a bundle, docs/compositing.md)."""

from __future__ import annotations

import onnx
import torch

from ..model.inpainter import CROP_MULTIPLE, InpainterNet
from . import onnx_export  # the module, not its function: tests swap `onnx_export.export_onnx` for a replay

EXPORT_SIDE = 64  # example crop side of the ONNX export
MAX_EXPORT_SIDE = 4096


def inpainter_onnx(model: InpainterNet) -> onnx.ModelProto:
    """F as an ONNX model proto: inputs "image" [1, 3, H, W], "mask" and "coverage" [1, 1, H, W], output
    "inpainted" [1, 3, H, W], with H and W dynamic multiples of CROP_MULTIPLE (batch fixed at 1)."""
    generator = torch.Generator().manual_seed(0)
    side = EXPORT_SIDE
    example = (torch.rand(1, 3, side, side, generator=generator), torch.ones(1, 1, side, side),
               torch.rand(1, 1, side, side, generator=generator))
    rows = torch.export.Dim("crop_rows", min=1, max=MAX_EXPORT_SIDE // CROP_MULTIPLE)
    cols = torch.export.Dim("crop_cols", min=1, max=MAX_EXPORT_SIDE // CROP_MULTIPLE)
    spatial = {2: CROP_MULTIPLE * rows, 3: CROP_MULTIPLE * cols}
    return onnx_export.export_onnx(model.eval(), example, ["image", "mask", "coverage"], ["inpainted"],
                                   dynamic_shapes={"image": spatial, "mask": spatial, "coverage": spatial})
