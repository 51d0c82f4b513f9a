"""FLAME as GaussianAvatars uses it: FLAME 2023 with 300 shape + 100 expression columns and 120 teeth vertices
(docs/import.md, "GaussianAvatars avatars").

GaussianAvatars binds its Gaussians to the triangles of FLAME plus a teeth extension it builds from the template:
two slabs (upper and lower teeth) behind the lips, 8 rows of 15 vertices, 168 triangles. The extension is rebuilt
here exactly, so triangle i of the avatar's `binding` is triangle i of this mesh, with the same vertex order (the
triangle frame depends on it). The model file is the user's own: a FLAME pickle read without running it
(flame_pkl) or the npz `gt-import flame` writes.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from gaussiantalker.sdk.errors import CheckpointError, ImportFormatError
from gaussiantalker.sdk.zip_reader import npz_shape, read_npz

from ...model.flame import FlameArrays
from ...model.flame_npz import load_flame_npz, parents_from_kintree
from ...model.flame_teeth import BASE_REGION, TEETH_REGION
from ..formats.flame_pkl import (
    FLAME_LAYOUT,
    N_EXPR_KEY,
    N_SHAPE_KEY,
    VERSION_KEY,
    detect_version,
    flame_arrays_from_pickle,
)

GA_N_SHAPE = 300
GA_N_EXPR = 100
GA_TEETH_VERTICES = 120
# FLAME's "lip_outside_ring_upper" / "lip_outside_ring_lower" vertex masks, in their order (mouth corner to corner
# through the midline, index 7): the teeth are built from these 15 pairs.
UPPER_LIP_RING = (1713, 1715, 1716, 1735, 1696, 1694, 1657, 3543, 2774, 2811, 2813, 2850, 2833, 2832, 2830)
LOWER_LIP_RING = (1576, 1577, 1773, 1774, 1795, 1802, 1865, 3503, 2948, 2905, 2898, 2881, 2880, 2713, 2712)
GA_N_VERTICES = FLAME_LAYOUT.n_vertices + GA_TEETH_VERTICES  # 5143
GA_N_FACES = FLAME_LAYOUT.n_faces + 2 * 84  # 10144
# FLAME releases before 2023 (as `gt-import flame` records them): same layout, another template and bases.
_OLDER_RELEASES = ("2017", "2019", "2020")

_RING = len(UPPER_LIP_RING)  # 15 vertices per teeth row
# Teeth rows (15 vertices each) in the order they are appended; local vertex index = 15 * row + column.
_ROWS = ("upper_root", "lower_root", "upper_edge", "lower_edge",
         "upper_root_back", "upper_edge_back", "lower_root_back", "lower_edge_back")
_UPPER_ROWS = ("upper_root", "upper_edge", "upper_root_back", "upper_edge_back")  # skinned to the neck joint
_LOWER_ROWS = ("lower_root", "lower_edge", "lower_root_back", "lower_edge_back")  # skinned to the jaw joint
_NECK_JOINT, _JAW_JOINT = 1, 2

# Teeth faces as strips. A strip joins row P to row Q with one quad per column pair (i, i+1), i = 0..13, and
# two triangles per quad. Corners: p = P[i], P = P[i+1], q = Q[i], Q = Q[i+1] (indices 0..3 below). The quads
# left of the midline column (i < 7) use one pattern and the rest another, so the diagonals mirror about the
# midline. A and C split along p-Q, B and D along P-q; A and B wind p -> P -> Q -> q, C and D the other way.
# Each pattern is the two triangles with their exact vertex order (the triangle frame starts at the first vertex).
_p, _P, _q, _Q = 0, 1, 2, 3
_PATTERNS = {
    "A": ((_p, _Q, _q), (_p, _P, _Q)),
    "B": ((_p, _P, _q), (_P, _Q, _q)),
    "C": ((_p, _q, _Q), (_p, _Q, _P)),
    "D": ((_p, _q, _P), (_P, _q, _Q)),
}
# (row P, row Q, pattern left of the midline, pattern right of it): front face, back face, biting edge.
_UPPER_STRIPS = (("upper_root", "upper_edge", "A", "B"),
                 ("upper_root_back", "upper_edge_back", "C", "D"),
                 ("upper_edge_back", "upper_edge", "D", "C"))
_LOWER_STRIPS = (("lower_edge", "lower_root", "B", "A"),
                 ("lower_root_back", "lower_edge_back", "A", "B"),
                 ("lower_edge_back", "lower_edge", "B", "A"))


# ------------------------------------------------------------------------------------------------- teeth


def teeth_faces_local() -> np.ndarray:
    """GaussianAvatars' 84 upper then 84 lower teeth triangles, local vertex indices 0..119. -> [168, 3] int64"""
    faces = [_strip(*strip) for strip in (*_UPPER_STRIPS, *_LOWER_STRIPS)]
    return np.concatenate(faces).astype(np.int64)


def _strip(row_p: str, row_q: str, left: str, right: str) -> np.ndarray:
    """The 28 triangles joining two teeth rows, quad by quad, each quad's two triangles in pattern order."""
    cols = np.arange(_RING - 1)
    p0, q0 = _RING * _ROWS.index(row_p) + cols, _RING * _ROWS.index(row_q) + cols
    corners = np.stack([p0, p0 + 1, q0, q0 + 1], axis=1)  # [14, 4]: p, P, q, Q
    out = [corners[i, np.asarray(_PATTERNS[left if i < _RING // 2 else right])] for i in cols]  # [2, 3] each
    return np.concatenate(out)


def _teeth_template(v_template: np.ndarray) -> np.ndarray:
    """The 120 teeth vertices from the raw template's lip rings, in _ROWS order (float64). -> [120, 3]"""
    upper = v_template[list(UPPER_LIP_RING)].astype(np.float64)
    lower = v_template[list(LOWER_LIP_RING)].astype(np.float64)
    d = np.linalg.norm(upper - lower, axis=1).mean()  # mean lip gap: the unit of every teeth size
    middle = (upper + lower) / 2
    middle[:, 1] = middle[:, 1].mean()  # one straight bite line
    middle[:, 2] -= 1.5 * d  # behind the lips
    up, back = np.array([0.0, d, 0.0]), np.array([0.0, 0.0, d])
    rows = {"upper_edge": middle + 0.1 * up}
    rows["upper_root"] = rows["upper_edge"] + 2 * up
    rows["lower_edge"] = middle - 0.1 * up - 0.4 * back  # the lower teeth sit a little further back
    rows["lower_root"] = rows["lower_edge"] - 2 * up
    for name in ("upper_root", "upper_edge", "lower_root", "lower_edge"):
        rows[f"{name}_back"] = rows[name] - back  # thickness d
    return np.concatenate([rows[name] for name in _ROWS])


def _row_vertices(names: tuple[str, ...]) -> np.ndarray:
    """Local indices of the vertices of the named rows."""
    return np.concatenate([_RING * _ROWS.index(name) + np.arange(_RING) for name in names])


def _check_flame_layout(arrays: FlameArrays) -> None:
    """CheckpointError naming the field unless `arrays` is FLAME's mesh (the lip rings index FLAME's vertices)."""
    if arrays.n_vertices != FLAME_LAYOUT.n_vertices:
        raise CheckpointError(f"FLAME 'v_template' has {arrays.n_vertices} vertices; GaussianAvatars' teeth are "
                              f"built on FLAME's {FLAME_LAYOUT.n_vertices}")
    if arrays.n_faces != FLAME_LAYOUT.n_faces:
        raise CheckpointError(f"FLAME 'faces' has {arrays.n_faces} triangles; GaussianAvatars' teeth are built on "
                              f"FLAME's {FLAME_LAYOUT.n_faces}")
    lips = np.asarray(UPPER_LIP_RING + LOWER_LIP_RING)
    if lips.max() >= arrays.n_vertices:  # implied by the vertex count; kept so the rings can never index past it
        raise CheckpointError(f"FLAME 'v_template' has no vertex {lips.max()} (a lip ring vertex)")


def add_gaussian_avatars_teeth(arrays: FlameArrays) -> FlameArrays:
    """FLAME plus GaussianAvatars' 120 teeth vertices and 168 faces, exactly as it builds them (5143 / 10144)."""
    _check_flame_layout(arrays)
    n_v, n_t = arrays.n_vertices, GA_TEETH_VERTICES
    upper, lower = list(UPPER_LIP_RING), list(LOWER_LIP_RING)
    shape_mean = (arrays.shapedirs[upper].astype(np.float64) + arrays.shapedirs[lower]) / 2  # [15, 3, n_shape]
    weights = np.zeros((n_t, arrays.lbs_weights.shape[1]), np.float32)
    weights[_row_vertices(_UPPER_ROWS), _NECK_JOINT] = 1.0
    weights[_row_vertices(_LOWER_ROWS), _JAW_JOINT] = 1.0
    faces = np.concatenate([arrays.faces, teeth_faces_local() + n_v])
    regions = np.concatenate([np.zeros(arrays.n_faces, np.int64), np.ones(GA_N_FACES - arrays.n_faces, np.int64)])
    return replace(
        arrays,
        v_template=_f32(np.concatenate([arrays.v_template, _teeth_template(arrays.v_template)])),
        shapedirs=_f32(np.concatenate([arrays.shapedirs, np.tile(shape_mean, (len(_ROWS), 1, 1))])),
        exprdirs=_f32(np.concatenate([arrays.exprdirs, np.zeros((n_t, *arrays.exprdirs.shape[1:]))])),
        posedirs=_f32(np.concatenate([arrays.posedirs, np.zeros((arrays.posedirs.shape[0], 3 * n_t))], axis=1)),
        J_regressor=_f32(np.concatenate([arrays.J_regressor, np.zeros((arrays.J_regressor.shape[0], n_t))], 1)),
        lbs_weights=_f32(np.concatenate([arrays.lbs_weights, weights])),
        faces=faces.astype(np.int64),
        regions=regions,
        region_names=(BASE_REGION, TEETH_REGION),
        teeth_anchors=np.zeros(0, np.int64),  # these vertices are built, not copies of lip vertices
    ).validate()


def fold_static_offset(arrays: FlameArrays, offset: np.ndarray) -> FlameArrays:
    """`arrays` with GaussianAvatars' per-vertex static_offset added to the template: it is added to the shaped
    vertices before the joint regressor and skinning, so folding it into the template is exact."""
    offset = np.asarray(offset)
    n_v = arrays.n_vertices
    if offset.shape not in ((n_v, 3), (1, n_v, 3)):
        raise ImportFormatError(f"'static_offset' has shape {list(offset.shape)}, expected [1, {n_v}, 3] or "
                                f"[{n_v}, 3] (one offset per vertex of FLAME with GaussianAvatars' teeth)")
    if offset.dtype.kind not in "fiu" or not np.isfinite(offset).all():
        raise ImportFormatError("'static_offset' must hold finite numbers")
    folded = arrays.v_template.astype(np.float64) + offset.reshape(n_v, 3)
    return replace(arrays, v_template=_f32(folded)).validate()


# ------------------------------------------------------------------------------------------------ loading


def load_gaussian_avatars_flame(path: str | Path) -> FlameArrays:
    """The user's FLAME model (a FLAME pickle, never run, or a FLAME npz) with GaussianAvatars' teeth added.

    It must have FLAME's mesh and 300 shape + 100 expression columns, as GaussianAvatars' FLAME 2023 has.
    """
    path = Path(path)
    try:
        with path.open("rb") as handle:
            head = handle.read(4)
    except OSError as exc:
        raise ImportFormatError(f"{path}: cannot read the FLAME model: {exc.strerror or exc}") from exc
    arrays = _load_npz(path) if head.startswith(b"PK") else _load_pickle(path)
    try:
        return add_gaussian_avatars_teeth(arrays)
    except CheckpointError as exc:  # the layout checks, told with the file they are about
        raise CheckpointError(f"{path}: {exc}") from None


def _refuse_older_release(path: Path, version: str, where: str) -> None:
    """ImportFormatError when the model is a FLAME release before 2023 (`version` as flame_pkl names it)."""
    if version.split(" ")[0] in _OLDER_RELEASES:
        raise ImportFormatError(
            f"{path}: {where} is {version!r}: GaussianAvatars tracks with FLAME 2023 (flame2023.pkl), and avatars "
            f"tracked with it do not fit FLAME {version}'s template; import flame2023.pkl instead")


def _load_pickle(path: Path) -> FlameArrays:
    """A FLAME pickle through flame_pkl's safe reader (its layout check names any wrong field); a file named as
    FLAME ships an older release (generic_model.pkl: FLAME 2020) is refused, as its npz would be."""
    _refuse_older_release(path, detect_version(path), "the file name says FLAME")
    raw = flame_arrays_from_pickle(path, FLAME_LAYOUT)
    return FlameArrays(
        v_template=_f32(raw["v_template"]),
        shapedirs=_f32(raw["shapedirs"][:, :, :GA_N_SHAPE]),
        exprdirs=_f32(raw["shapedirs"][:, :, GA_N_SHAPE:]),
        posedirs=_f32(raw["posedirs"].reshape(-1, raw["posedirs"].shape[2]).T),  # [36, V*3], as load_flame_npz
        J_regressor=_f32(raw["J_regressor"]),
        lbs_weights=_f32(raw["weights"]),
        faces=np.ascontiguousarray(raw["f"], dtype=np.int64),
        parents=parents_from_kintree(raw["kintree_table"]),
    ).validate()


def _load_npz(path: Path) -> FlameArrays:
    """A FLAME npz with exactly 300 shape + 100 expression columns, not one recorded as FLAME 2020."""
    columns = _npz_member_shape(path, "shapedirs")
    info = _npz_info(path)
    _refuse_older_release(path, str(info.get(VERSION_KEY, "")), f"'{VERSION_KEY}'")
    n_shape = int(info.get(N_SHAPE_KEY, GA_N_SHAPE))
    total = columns[2] if len(columns) == 3 else -1
    if n_shape != GA_N_SHAPE or total != GA_N_SHAPE + GA_N_EXPR:
        found = f"{total} columns: {n_shape} shape + {total - n_shape} expression" if total >= 0 else \
            f"shape {list(columns)}"
        raise ImportFormatError(f"{path}: 'shapedirs' has {found}; GaussianAvatars needs "
                                f"{GA_N_SHAPE} + {GA_N_EXPR} (FLAME 2023)")
    return load_flame_npz(path, GA_N_SHAPE, GA_N_EXPR, shape_columns=GA_N_SHAPE)


def _npz_member_shape(path: Path, key: str) -> tuple[int, ...]:
    """The shape of one array of an npz from its header, without reading the array."""
    shape = npz_shape(path, key, ImportFormatError, "a FLAME model npz")
    if shape is None:
        raise ImportFormatError(f"{path}: not a FLAME npz: no '{key}'")
    return shape


def _npz_info(path: Path) -> dict[str, object]:
    """The version and column counts `gt-import flame` records (absent in other FLAME npz files): a string and
    two whole numbers, each one value."""
    info = read_npz(path, ImportFormatError, "a FLAME model npz", (VERSION_KEY, N_SHAPE_KEY, N_EXPR_KEY))
    for key, value in info.items():
        kinds = "US" if key == VERSION_KEY else "iu"
        if value.size != 1 or value.dtype.kind not in kinds:
            raise ImportFormatError(f"{path}: '{key}' must be one {'string' if kinds == 'US' else 'whole number'}, "
                                    f"got {value.dtype.str} {list(value.shape)}")
    return {key: value.item() for key, value in info.items()}


def _f32(array: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(array, dtype=np.float32)
