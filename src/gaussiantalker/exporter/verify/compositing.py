"""The torch side of compositing: F through the torch generator, and the composited reference frames that
`--verify` holds the runtime's against (docs/compositing.md)."""

from __future__ import annotations

import numpy as np
import torch

from gaussiantalker.runtime.composite import Inpainter, composite, opencv_fallback

from ..model.inpainter import InpainterNet


def torch_inpainter(model: InpainterNet | None) -> Inpainter:
    """F on a crop through the torch generator (the reference for the `inpaint` graph), or the OpenCV fallback."""
    if model is None:
        return opencv_fallback

    @torch.no_grad()
    def inpaint(x: np.ndarray, mask: np.ndarray, render: np.ndarray) -> np.ndarray:
        image = torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1)))[None]
        out = model(image, torch.from_numpy(mask)[None, None], torch.from_numpy(render[..., 3].copy())[None, None])
        return out[0].permute(1, 2, 0).numpy()

    return inpaint


def composite_reference(head: np.ndarray, reference: np.ndarray, mask: np.ndarray,
                        model: InpainterNet | None) -> np.ndarray:
    """The composited frame with the torch F (what the runtime's frame is verified against)."""
    return composite(head, reference, mask, torch_inpainter(model))
