"""The semantic pass: each Gaussian drawn in its parent triangle's region colour (the paper's auxiliary map M_aux),
for debugging a binding and as the rendered face's own mask (docs/compositing.md, "Semantic pass")."""

from __future__ import annotations

import numpy as np

from gaussiantalker.sdk.bundle import Bundle
from gaussiantalker.sdk.errors import BundleError

# Region colours in region-id order, then repeating: distinct hues, none black (black is "no Gaussian").
REGION_PALETTE = np.array([
    (0.90, 0.60, 0.45), (0.85, 0.10, 0.20), (1.00, 1.00, 0.85), (0.35, 0.00, 0.10), (0.60, 0.90, 1.00),
    (0.10, 0.30, 0.90), (0.95, 0.80, 0.10), (0.45, 0.25, 0.05), (0.20, 0.75, 0.30), (0.70, 0.30, 0.80),
    (0.00, 0.60, 0.60), (0.55, 0.55, 0.55),
], dtype=np.float32)


class Regions:
    """A bundle's region names and per-Gaussian region ids, checked at load."""

    def __init__(self, bundle: Bundle) -> None:
        names = bundle.manifest.get("regions")
        if not (isinstance(names, list) and names and all(isinstance(n, str) for n in names)):
            raise BundleError(f"{bundle.path}: manifest 'regions' must be a list of region names")
        self.names = tuple(names)
        self.ids = bundle.buffer("gaussian_regions").astype(np.int64)
        if self.ids.ndim != 1 or (self.ids.size and not 0 <= self.ids.min() <= self.ids.max() < len(self.names)):
            raise BundleError(f"{bundle.path}: buffer 'gaussian_regions' must be [N] ids in 0..{len(self.names) - 1}")

    @property
    def colors(self) -> np.ndarray:
        """Colour of each region [R, 3] (REGION_PALETTE, repeating)."""
        return REGION_PALETTE[np.arange(len(self.names)) % len(REGION_PALETTE)]

    def gaussian_colors(self, count: int) -> np.ndarray:
        """Region colour of each of the frame's `count` Gaussians [N, 3]."""
        self._check_count(count)
        return self.colors[self.ids]

    def one_hot(self, count: int, first: int) -> np.ndarray:
        """Colours [N, 3] selecting regions first..first+2 into the red, green and blue channels."""
        self._check_count(count)
        colors = np.zeros((count, 3), np.float32)
        for channel in range(3):
            colors[self.ids == first + channel, channel] = 1.0
        return colors

    def _check_count(self, count: int) -> None:
        if count != self.ids.size:
            raise BundleError(f"buffer 'gaussian_regions' labels {self.ids.size} Gaussians but the deformation graph "
                              f"outputs {count}")
