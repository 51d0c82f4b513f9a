"""Vertices of a blendshape rig that move as the midpoint of two others: what a subdivided mesh's edge vertices do.

A LAM avatar's head mesh is FLAME subdivided once (each triangle into four), and its morph targets are the coarse
mesh's, carried to every edge vertex as the mean of the edge's two ends. Found here from the rig's triangles and
numbers, so that the ARKit deformation graph stores the morph targets of the other vertices only and derives these
(docs/deformation.md, "Midpoint vertices"): 4x fewer morph values on LAM's avatars.

A vertex v is derived from two of its mesh neighbours (a, b) when its rest position and every morph target equal
their mean within MIDPOINT_TOLERANCE_M; a and b are stored themselves (one level: no derivation waits on another).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

# How far (metres, per coordinate, per morph target at weight 1) a derived vertex may sit from what the rig stores for
# it: 10 µm, a hundredth of a pixel at LAM's portrait camera (a focal length of 1,452 px at 1.5 m). LAM's p2-1 keeps
# its edge vertices' morphs within 2.0e-6 m of the mean (float32 rounding of the renderer's own averaging).
MIDPOINT_TOLERANCE_M = 1e-5
# Mesh neighbours of a vertex tried as its two ends (a subdivided mesh's edge vertex has 6: its ends and four edge
# vertices); a vertex with more has only its first ones tried, which bounds the pairs at V x 120.
MAX_NEIGHBOURS = 16
_VERTEX_BLOCK = 512  # vertices whose neighbour pairs are compared at a time (at most 512 x 120 pairs)
# The last tables found, by a digest of the arrays they were found in: an export that derives midpoints and orders its
# Gaussians spatially asks twice for the same rig (0.3-0.6 s each on LAM's avatars).
_FOUND: dict[bytes, np.ndarray] = {}
_FOUND_KEPT = 4


def _neighbours(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """[V, MAX_NEIGHBOURS] each vertex's mesh neighbours (the ends of its edges), -1 where it has fewer."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges = np.unique(np.concatenate([edges, edges[:, ::-1]]), axis=0)  # both directions, sorted by vertex
    edges = edges[edges[:, 0] != edges[:, 1]]
    start = np.searchsorted(edges[:, 0], np.arange(n_vertices))
    rank = np.arange(len(edges)) - start[edges[:, 0]]
    edges, rank = edges[rank < MAX_NEIGHBOURS], rank[rank < MAX_NEIGHBOURS]
    table = np.full((n_vertices, MAX_NEIGHBOURS), -1, np.int64)
    table[edges[:, 0], rank] = edges[:, 1]
    return table


def _fitting_pairs(rest: np.ndarray, morphs: np.ndarray, near: np.ndarray, block: np.ndarray, tolerance: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(v, a, b, morph error) of the vertices `block` whose neighbour pair (a < b) fits within `tolerance`."""
    first, second = np.triu_indices(MAX_NEIGHBOURS, 1)
    a, b = near[block][:, first], near[block][:, second]  # [block, pairs]
    vertex = np.broadcast_to(block[:, None], a.shape)
    real = (a >= 0) & (b >= 0)
    vertex, a, b = vertex[real], a[real], b[real]
    fits = np.abs(rest[a] + rest[b] - 2 * rest[vertex]).max(-1, initial=0.0) <= 2 * tolerance
    vertex, a, b = vertex[fits], np.minimum(a[fits], b[fits]), np.maximum(a[fits], b[fits])
    morph_error = np.abs(morphs[:, a] + morphs[:, b] - 2 * morphs[:, vertex]).max((0, 2), initial=0.0) / 2
    fits = morph_error <= tolerance
    return vertex[fits], a[fits], b[fits], morph_error[fits]


def find_midpoints(rest: np.ndarray, morphs: np.ndarray, faces: np.ndarray,
                   tolerance: float = MIDPOINT_TOLERANCE_M) -> np.ndarray:
    """[M, 3] int64 rows (v, a, b): vertex v of rest [V, 3] and morphs [K, V, 3] is the midpoint of its mesh
    neighbours a < b (faces [F, 3]), which are not derived themselves; sorted by v. Empty [0, 3] when none is."""
    rest = np.asarray(rest, np.float64)
    morphs = np.asarray(morphs, np.float64)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    key = _digest(rest, morphs, faces, np.float64(tolerance))
    if key not in _FOUND:
        if len(_FOUND) >= _FOUND_KEPT:
            del _FOUND[next(iter(_FOUND))]
        _FOUND[key] = _found(rest, morphs, faces, tolerance)
    return _FOUND[key].copy()


def _digest(*arrays: np.ndarray) -> bytes:
    """A digest of the arrays' shapes and bytes."""
    digest = hashlib.blake2b(digest_size=32)
    for array in arrays:
        digest.update(repr(array.shape).encode())
        digest.update(np.ascontiguousarray(array).tobytes())
    return digest.digest()


def _found(rest: np.ndarray, morphs: np.ndarray, faces: np.ndarray, tolerance: float) -> np.ndarray:
    """find_midpoints's table, computed."""
    n_vertices = rest.shape[0]
    if n_vertices < 3 or not len(faces):
        return np.zeros((0, 3), np.int64)
    near = _neighbours(faces, n_vertices)
    found = [_fitting_pairs(rest, morphs, near, block, tolerance)
             for block in np.array_split(np.arange(n_vertices), -(-n_vertices // _VERTEX_BLOCK))]
    vertex, a, b, morph_error = (np.concatenate(column) for column in zip(*found, strict=True))
    best = np.lexsort((b, a, morph_error, vertex))  # per vertex, its best-fitting pair first
    vertex, a, b = vertex[best], a[best], b[best]
    first_of_vertex = np.r_[True, vertex[1:] != vertex[:-1]] if len(vertex) else np.zeros(0, bool)
    return _one_level(np.stack([vertex, a, b], 1)[first_of_vertex], n_vertices)


def _one_level(candidates: np.ndarray, n_vertices: int) -> np.ndarray:
    """The candidates (v, a, b) kept so that no derived vertex is another's end. First those whose ends are no
    candidates themselves (a subdivided mesh's edge vertices, whose ends are the coarse vertices), then the rest
    in vertex order while they do not clash with what is kept."""
    is_candidate = np.zeros(n_vertices, bool)
    is_candidate[candidates[:, 0]] = True
    derived = np.zeros(n_vertices, bool)
    used_as_end = np.zeros(n_vertices, bool)
    clean = ~is_candidate[candidates[:, 1]] & ~is_candidate[candidates[:, 2]]
    for v, a, b in candidates[clean]:
        derived[v] = True
        used_as_end[[a, b]] = True
    for v, a, b in candidates[~clean]:
        if not used_as_end[v] and not derived[a] and not derived[b]:
            derived[v] = True
            used_as_end[[a, b]] = True
    kept = candidates[derived[candidates[:, 0]]]
    return kept[np.argsort(kept[:, 0], kind="stable")].astype(np.int64)


@dataclass(frozen=True)
class MorphRows:
    """Where each Gaussian's morph targets come from: `sources` (vertex ids whose morph targets are stored, in that
    order), the derived rows after them (vertex ids `derived`, each the mean of stored rows `ends` [2, M]), and
    `gaussian_rows` [N]: each Gaussian's row in [sources; derived]. `kept_prefix`: when the Gaussians' rows are
    the first `kept_prefix` sources and then every derived row in order, the graph slices instead of gathering."""

    sources: np.ndarray
    derived: np.ndarray
    ends: np.ndarray
    gaussian_rows: np.ndarray
    kept_prefix: int | None


def morph_rows(vertex: np.ndarray, midpoints: np.ndarray) -> MorphRows:
    """The rows of Gaussians bound to vertices `vertex` [N], given the rig's `find_midpoints` rows."""
    vertex = np.asarray(vertex, np.int64)
    derived_of = dict(zip(midpoints[:, 0].tolist(), midpoints[:, 1:].tolist(), strict=True))
    in_order = list(dict.fromkeys(vertex.tolist()))  # each vertex once, in the Gaussians' order
    derived = np.array([v for v in in_order if v in derived_of], np.int64)
    direct = [v for v in in_order if v not in derived_of]
    ends = sorted({end for v in derived.tolist() for end in derived_of[v]} - set(direct))
    sources = np.array(direct + ends, np.int64)
    row_of = {v: k for k, v in enumerate(sources.tolist())}
    row_of.update({v: len(sources) + k for k, v in enumerate(derived.tolist())})
    # each pair nearest row first (a midpoint is symmetric in its ends; sorted pairs deflate better)
    end_rows = np.sort(np.array([[row_of[end] for end in derived_of[v]] for v in derived.tolist()],
                                np.int64).reshape(-1, 2), axis=1)
    gaussian_rows = np.array([row_of[v] for v in vertex.tolist()], np.int64)
    sliced = np.concatenate([np.arange(len(direct)), len(sources) + np.arange(len(derived))])
    kept_prefix = len(direct) if np.array_equal(gaussian_rows, sliced) else None
    return MorphRows(sources, derived, end_rows.T.copy(), gaussian_rows, kept_prefix)


__all__ = ["MIDPOINT_TOLERANCE_M", "MAX_NEIGHBOURS", "MorphRows", "find_midpoints", "morph_rows"]
