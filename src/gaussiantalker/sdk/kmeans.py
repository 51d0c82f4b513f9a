"""k-means over float vectors: the codebook the `vq` buffer codec stores (sdk/codecs.py; docs/bundle-format.md,
"Codecs"). Encoder-side only: a reader decodes a codebook with a table lookup and never runs this.

Hand-written: a few lines of numpy, and no dependency of the package has k-means (scipy and scikit-learn, which
do, are not ones). Deterministic: k-means++ seeding from a fixed seed, then a fixed number of Lloyd steps, so an
export is byte-identical run to run on one machine.
"""

from __future__ import annotations

import numpy as np

# Lloyd steps after the seeding: the number the codings of LAM's p2-1 were measured with (docs/precision.md,
# "Speakers differ").
KMEANS_ITERATIONS = 20
# Vectors whose distances to every centre are computed at once: the memory is BLOCK x k doubles.
BLOCK = 2048


def closest(vectors: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Index [N] of each vector's nearest centre (squared distance as ||c||^2 - 2 x.c; ties to the lower index),
    in blocks of BLOCK vectors."""
    norms = (centres**2).sum(1)[None, :]
    out = [np.argmin(norms - 2.0 * vectors[start:start + BLOCK] @ centres.T, axis=1)
           for start in range(0, len(vectors), BLOCK)]
    return np.concatenate(out) if out else np.zeros(0, np.int64)


def kmeans(vectors: np.ndarray, k: int, iterations: int = KMEANS_ITERATIONS, seed: int = 0
           ) -> tuple[np.ndarray, np.ndarray]:
    """(centres [k, D] float64, each vector's index [N]) of vectors [N >= 1, D]: k-means++ seeding from `seed`, then
    `iterations` Lloyd steps (an empty cluster keeps its centre)."""
    x = np.asarray(vectors, np.float64)
    if x.ndim != 2 or len(x) == 0 or k < 1:
        raise ValueError(f"kmeans needs vectors [N >= 1, D] and k >= 1, got {x.shape} and {k}")
    rng = np.random.default_rng(seed)
    centres = np.empty((k, x.shape[1]))
    centres[0] = x[rng.integers(len(x))]
    nearest = ((x - centres[0]) ** 2).sum(1)
    for i in range(1, k):
        total = nearest.sum()
        pick = rng.choice(len(x), p=nearest / total) if total > 0 else rng.integers(len(x))
        centres[i] = x[pick]
        nearest = np.minimum(nearest, ((x - centres[i]) ** 2).sum(1))
    index = closest(x, centres)
    for _ in range(iterations):
        counts = np.bincount(index, minlength=k)
        sums = np.zeros_like(centres)
        np.add.at(sums, index, x)
        filled = counts > 0
        centres[filled] = sums[filled] / counts[filled, None]
        index = closest(x, centres)
    return centres, index


__all__ = ["KMEANS_ITERATIONS", "closest", "kmeans"]
