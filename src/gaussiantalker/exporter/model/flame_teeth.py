"""The teeth extension of a FLAME-structured head: upper and lower teeth (and a closed dark mouth pocket) as new
vertices that copy their anchor lip vertices' bases and skinning, so they move with the lips (docs/demo-speaker.md)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from .flame import N_JOINTS, FlameArrays, as_float32

TEETH_REGION = "teeth"
MOUTH_INTERIOR_REGION = "mouth_interior"
BASE_REGION = "skin"


def add_teeth(
    arrays: FlameArrays,
    upper_lip_idx: Sequence[int],
    lower_lip_idx: Sequence[int],
    depth: float,
    height: float,
    *,
    interior: bool = True,
) -> FlameArrays:
    """Append upper/lower teeth (and a closed dark mouth pocket) that move in sync with their anchor lip rows.

    The lip rows run along the mouth in the same order (equal length). Each new vertex copies its anchor's
    shapedirs/exprdirs/posedirs rows and LBS weights and has no J_regressor weight, so it gets no blendshapes
    or skinning of its own (paper, Implementation Details); only its template position differs.
    depth/height are in metres, in FLAME's frame (y up, face toward +z): teeth sit `depth` behind the lip line.
    """
    upper = np.asarray(upper_lip_idx, dtype=np.int64)
    lower = np.asarray(lower_lip_idx, dtype=np.int64)
    n_v = arrays.n_vertices
    if upper.ndim != 1 or upper.shape != lower.shape or upper.size < 2:
        raise ValueError("upper_lip_idx and lower_lip_idx must be equal-length rows of at least 2 vertices")
    if min(upper.min(), lower.min()) < 0 or max(upper.max(), lower.max()) >= n_v:
        raise ValueError(f"lip vertex indices must lie in [0, {n_v})")
    rows, strips, corners = _teeth_layout(upper, lower, depth, height, interior)
    return _append_anchored(arrays, rows, strips, corners)


# A row is (anchor vertex per entry [n], template offset from the anchor [3]); a strip joins two rows with
# quads and has a region name and the direction its normals should face.
_Row = tuple[np.ndarray, np.ndarray]
_Strip = tuple[str, int, int, tuple[float, float, float]]
# A single triangle given as three (row, entry) references (entry -1: the row's last), with its region name.
_Corner = tuple[str, tuple[tuple[int, int], tuple[int, int], tuple[int, int]]]


def _teeth_layout(
    upper: np.ndarray, lower: np.ndarray, depth: float, height: float, interior: bool
) -> tuple[list[_Row], list[_Strip], list[_Corner]]:
    """Rows of new vertices behind the lip rows, the strips (teeth faces, inner pocket) joining them and the
    single triangles closing the pocket's sides."""
    back = np.array([0.0, 0.0, -1.0])
    up = np.array([0.0, 1.0, 0.0])
    lower_depth = 1.25 * depth  # lower incisors sit behind the upper ones (overbite), so they never z-fight
    rows: list[_Row] = [
        (upper, height * up + depth * back),  # 0: upper gum line, hidden behind the upper lip
        (upper, -0.25 * height * up + depth * back),  # 1: upper incisal edge, just below the lip line
        (upper, -0.25 * height * up + 2.0 * depth * back),  # 2: upper biting surface
        (lower, -height * up + lower_depth * back),  # 3: lower gum line
        (lower, 0.1 * height * up + lower_depth * back),  # 4: lower incisal edge
        (lower, 0.1 * height * up + (lower_depth + depth) * back),  # 5: lower biting surface
    ]
    strips: list[_Strip] = [
        (TEETH_REGION, 0, 1, (0.0, 0.0, 1.0)),
        (TEETH_REGION, 1, 2, (0.0, -1.0, 0.0)),
        (TEETH_REGION, 3, 4, (0.0, 0.0, 1.0)),
        (TEETH_REGION, 4, 5, (0.0, 1.0, 0.0)),
    ]
    corners: list[_Corner] = []
    if interior:  # a closed dark pocket behind the lips that stretches as the jaw opens (docs/demo-speaker.md):
        rows.append((upper, 1.5 * height * up + 3.0 * depth * back))  # 6: top of the back wall
        rows.append((lower, -1.5 * height * up + 3.0 * depth * back))  # 7: bottom of the back wall
        rows.append((upper, 0.0 * up))  # 8: the upper lip's inner edge (a copy of the lip row)
        rows.append((lower, 0.0 * up))  # 9: the lower lip's inner edge
        strips.append((MOUTH_INTERIOR_REGION, 6, 7, (0.0, 0.0, 1.0)))  # back wall
        strips.append((MOUTH_INTERIOR_REGION, 8, 6, (0.0, -1.0, 0.0)))  # roof, from the upper lip to the wall
        strips.append((MOUTH_INTERIOR_REGION, 9, 7, (0.0, 1.0, 0.0)))  # floor, from the lower lip to the wall
        # Side walls at each mouth corner, where the lip rows meet: (lip corner, wall top, wall bottom).
        corners = [(MOUTH_INTERIOR_REGION, ((8, end), (6, end), (7, end))) for end in (0, -1)]
    return rows, strips, corners


def _append_anchored(arrays: FlameArrays, rows: list[_Row], strips: list[_Strip], corners: list[_Corner] = ()
                     ) -> FlameArrays:
    """Append the rows as anchored vertex copies and the strips and corner triangles as faces with their region
    labels."""
    names = list(arrays.region_names) or [BASE_REGION]
    regions = arrays.regions if arrays.regions is not None else np.zeros(arrays.n_faces, dtype=np.int64)
    anchor_idx = np.concatenate([anchor for anchor, _ in rows])  # [T]
    positions = np.concatenate([arrays.v_template[anchor] + offset for anchor, offset in rows])  # [T, 3]
    starts = arrays.n_vertices + np.cumsum([0] + [anchor.size for anchor, _ in rows])
    all_pos = np.concatenate([arrays.v_template, positions])
    new_faces, new_regions = [], []
    for region, row_a, row_b, facing in strips:
        if region not in names:
            names.append(region)
        ids_a = np.arange(starts[row_a], starts[row_a + 1])
        ids_b = np.arange(starts[row_b], starts[row_b + 1])
        faces = _orient(_strip_faces(ids_a, ids_b), all_pos, np.asarray(facing))
        new_faces.append(faces)
        new_regions.append(np.full(len(faces), names.index(region), dtype=np.int64))
    for region, refs in corners:
        if region not in names:
            names.append(region)
        new_faces.append(np.array([[starts[row] + entry % rows[row][0].size for row, entry in refs]], np.int64))
        new_regions.append(np.array([names.index(region)], np.int64))
    return _with_vertices(arrays, anchor_idx, positions, new_faces, new_regions, names, regions)


def _strip_faces(row_a: np.ndarray, row_b: np.ndarray) -> np.ndarray:
    """Two triangles per quad between two equal-length vertex rows. -> [2(n-1), 3] int64"""
    a0, a1, b0, b1 = row_a[:-1], row_a[1:], row_b[:-1], row_b[1:]
    return np.concatenate([np.stack([a0, a1, b1], 1), np.stack([a0, b1, b0], 1)]).astype(np.int64)


def _orient(faces: np.ndarray, positions: np.ndarray, facing: np.ndarray) -> np.ndarray:
    """Flip a strip's winding so its mean normal points along `facing`."""
    p = positions[faces]  # [F, 3, 3]
    normals = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return faces[:, ::-1].copy() if normals.sum(0) @ facing < 0 else faces


def _with_vertices(
    arrays: FlameArrays,
    anchor_idx: np.ndarray,
    positions: np.ndarray,
    new_faces: list[np.ndarray],
    new_regions: list[np.ndarray],
    names: list[str],
    regions: np.ndarray,
) -> FlameArrays:
    """New FlameArrays with vertices appended that copy every per-vertex basis row of their anchors."""
    pose_cols = (3 * anchor_idx[:, None] + np.arange(3)).reshape(-1)  # posedirs columns of the anchors
    j_reg = np.concatenate([arrays.J_regressor, np.zeros((N_JOINTS, anchor_idx.size), np.float32)], 1)
    return replace(
        arrays,
        v_template=as_float32(np.concatenate([arrays.v_template, positions])),
        shapedirs=as_float32(np.concatenate([arrays.shapedirs, arrays.shapedirs[anchor_idx]])),
        exprdirs=as_float32(np.concatenate([arrays.exprdirs, arrays.exprdirs[anchor_idx]])),
        posedirs=as_float32(np.concatenate([arrays.posedirs, arrays.posedirs[:, pose_cols]], 1)),
        J_regressor=as_float32(j_reg),
        lbs_weights=as_float32(np.concatenate([arrays.lbs_weights, arrays.lbs_weights[anchor_idx]])),
        faces=np.concatenate([arrays.faces, *new_faces]).astype(np.int64),
        regions=np.concatenate([regions, *new_regions]).astype(np.int64),
        region_names=tuple(names),
        teeth_anchors=np.concatenate([arrays.teeth_anchors, anchor_idx]).astype(np.int64),
    ).validate()
