"""A procedurally generated, FLAME-structured demo head, so that everything runs without the licensed FLAME file.

Same 5 joints and kinematic tree, same kinds of bases (shape, expression, pose correctives, LBS weights, joint
regressor) as FLAME, in FLAME's metric frame (metres, y up, face toward +z), with ~4.4k vertices: a skull with a
chin and jaw, a nose, ears, a mouth cut open along the lip line (upper and lower lip are separate surfaces, the
lower one skinned to the jaw), lips, teeth and inner mouth (`add_teeth`), two eyeballs skinned to the eye
joints, brows and hair, each face labelled with a region from `REGION_NAMES`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..model.flame import POSE_FEATURE_DIM, FlameArrays
from ..model.flame_teeth import add_teeth

REGION_NAMES = ("skin", "lips", "teeth", "mouth_interior", "eye_white", "iris", "brows", "hair")
# sRGB colour per region, in REGION_NAMES order.
REGION_COLORS = (
    (0.87, 0.68, 0.56),  # skin
    (0.72, 0.27, 0.30),  # lips
    (0.95, 0.94, 0.88),  # teeth
    (0.22, 0.05, 0.06),  # mouth_interior
    (0.95, 0.95, 0.95),  # eye_white
    (0.18, 0.11, 0.06),  # iris
    (0.22, 0.14, 0.09),  # brows
    (0.28, 0.18, 0.11),  # hair
)
SKIN, LIPS, TEETH, MOUTH_INTERIOR, EYE_WHITE, IRIS, BROWS, HAIR = range(len(REGION_NAMES))

# ---- layout (metres) ----
N_COLUMNS = 64  # samples around the head
COLUMN_FRONT_DENSITY = 0.65  # azimuth warp phi = s - a sin(s): columns (1 - a) times denser at the face
MOUTH_Y = -0.045  # height of the lip line (the mouth cut)
MOUTH_HALF_WIDTH = 0.024  # mouth corners at x = +-this
EYE_X, EYE_Y = 0.032, 0.020  # eyeball centres at (+-EYE_X, EYE_Y, z from the socket depth)
EYE_RADIUS = 0.0125
EYE_PROTRUSION = 0.005  # how far the eyeball's front pole sits in front of the socket's skin
IRIS_ANGLE = 0.38  # iris = eyeball faces within this angle (rad) of the eye's forward axis
TEETH_DEPTH = 0.005  # teeth sit this far behind the lip line
TEETH_HEIGHT = 0.008
JAW_HINGE = (0.06, -0.010, 0.008)  # (|x|, y, z) of the temporomandibular joints; the jaw joint is their mean
NECK_JOINT_Y = -0.102
EXPR_SIGMA_MM = 3.0  # a 1-sigma expression coefficient moves the vertices it targets by about this much
SHAPE_SIGMA_MM = 4.0
POSE_CORRECTIVE_MM = 1.0


def make_demo_head(n_shape: int = 20, n_expr: int = 20, seed: int = 0) -> FlameArrays:
    """Build the demo head (deterministic for a given seed); the seed only drives the random extra bases."""
    rng = np.random.default_rng(seed)
    skin = _build_skin()
    eyes = [_eyeball(sign, skin) for sign in (1.0, -1.0)]  # FLAME: left eye is the subject's left, +x
    mesh = _assemble(skin, eyes)
    weights = _lbs_weights(mesh)
    arrays = FlameArrays(
        v_template=mesh.positions.astype(np.float32),
        shapedirs=_shapedirs(mesh, n_shape, rng).astype(np.float32),
        exprdirs=_exprdirs(mesh, n_expr, rng).astype(np.float32),
        posedirs=_posedirs(mesh, weights, rng).astype(np.float32),
        J_regressor=_joint_regressor(mesh).astype(np.float32),
        lbs_weights=weights.astype(np.float32),
        faces=mesh.faces,
        regions=mesh.regions,
        region_names=REGION_NAMES,
    ).validate()
    upper, lower = skin.lip_rows
    return add_teeth(arrays, upper, lower, TEETH_DEPTH, TEETH_HEIGHT)


def demo_lip_vertices() -> tuple[np.ndarray, np.ndarray]:
    """Upper- and lower-lip vertex rows along the mouth cut (corners shared, ordered -x to +x) [n], [n]."""
    upper, lower = _build_skin().lip_rows
    return upper.copy(), lower.copy()


# --------------------------------------------------------------------------------------------- helpers


def _smoothstep(edge0: float, edge1: float, x: np.ndarray) -> np.ndarray:
    """Hermite step from 0 at edge0 to 1 at edge1 (edge0 > edge1 gives a falling step)."""
    t = np.clip((x - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _gauss(x: np.ndarray, y: np.ndarray, cx: float, cy: float, sx: float, sy: float) -> np.ndarray:
    return np.exp(-(((x - cx) / sx) ** 2) - ((y - cy) / sy) ** 2)


def _catmull_rom(keys: np.ndarray, samples_per_segment: int) -> np.ndarray:
    """Dense smooth curve through keyframe rows [K, D] -> [(K-1)*n + 1, D]."""
    p = np.concatenate([keys[:1], keys, keys[-1:]])
    t = np.linspace(0.0, 1.0, samples_per_segment, endpoint=False)[:, None]
    out = []
    for i in range(1, len(p) - 2):
        p0, p1, p2, p3 = p[i - 1], p[i], p[i + 1], p[i + 2]
        out.append(
            0.5 * (2 * p1 + (p2 - p0) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t**2 + (3 * p1 - p0 - 3 * p2 + p3) * t**3)
        )
    out.append(keys[-1:])
    return np.concatenate(out)


# ------------------------------------------------------------------------------------------------- skin


def _profile_keys() -> np.ndarray:
    """Keyframes (y, half-width, front depth, back depth) of the head's horizontal rings, crown to neck."""
    theta = np.array([0.0, 0.3, 0.6, 0.9, 1.2])  # cranium: an ellipsoid cap
    cranium = np.stack(
        [0.022 + 0.096 * np.cos(theta), 0.073 * np.sin(theta), 0.090 * np.sin(theta), 0.099 * np.sin(theta)], 1
    )
    face = np.array(
        [
            [0.040, 0.0745, 0.0905, 0.1000],  # brow
            [0.015, 0.0740, 0.0900, 0.0985],  # eyes
            [-0.015, 0.0715, 0.0880, 0.0930],  # cheekbones
            [-0.045, 0.0630, 0.0850, 0.0800],  # mouth
            [-0.068, 0.0540, 0.0800, 0.0680],  # chin
            [-0.084, 0.0460, 0.0700, 0.0600],  # chin bottom
            [-0.096, 0.0440, 0.0520, 0.0540],  # under the chin
            [-0.108, 0.0445, 0.0440, 0.0510],  # top of the neck
            [-0.130, 0.0470, 0.0440, 0.0520],
            [-0.160, 0.0500, 0.0460, 0.0540],  # neck base (closed by a fan: _close_neck)
        ]
    )
    return np.concatenate([cranium, face])


def _row_spacing(y: np.ndarray) -> np.ndarray:
    """Wanted distance between rings along the face profile: fine at the lips, medium on the face."""
    face = _smoothstep(0.075, 0.055, y) * _smoothstep(-0.105, -0.09, y)
    mouth = _smoothstep(0.02, 0.012, np.abs(y - MOUTH_Y))
    return 0.009 - 0.0045 * face - 0.0017 * mouth


def _profile_rows() -> np.ndarray:
    """Ring parameters [R, 4] (y, half-width, front depth, back depth), one ring exactly at the lip line."""
    dense = _catmull_rom(_profile_keys(), 60)
    arc = np.linalg.norm(np.diff(dense[:, [0, 2]], axis=0), axis=1)  # along the front profile (y, z)
    u = np.concatenate([[0.0], np.cumsum(arc / _row_spacing(dense[1:, 0]))])  # in units of rows
    mouth_u = np.interp(MOUTH_Y, dense[::-1, 0], u[::-1])
    k = np.arange(-np.floor(mouth_u - 0.6), np.floor(u[-1] - mouth_u) + 1)
    targets = mouth_u + k
    return np.stack([np.interp(targets, u, dense[:, d]) for d in range(4)], 1)


def _azimuths() -> np.ndarray:
    """Column azimuths [C], 0 = facing +z, +pi/2 = +x; symmetric, denser at the face."""
    s = -np.pi + 2.0 * np.pi * np.arange(N_COLUMNS) / N_COLUMNS
    return s - COLUMN_FRONT_DENSITY * np.sin(s)


def _nose(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Forward displacement of the nose: a ridge growing from the bridge to the tip, plus the nostril wings."""
    t = np.clip((0.024 - y) / 0.040, 0.0, 1.0)  # 0 at the bridge, 1 at the tip (y = -0.016)
    height = (0.003 + 0.019 * t**1.6) * _smoothstep(0.034, 0.022, y)
    height = np.where(y < -0.016, 0.022 * np.exp(-(((y + 0.016) / 0.0075) ** 2)), height)
    width = 0.0065 + 0.0065 * t
    ridge = height * np.exp(-((x / width) ** 2))
    wings = 0.0085 * (_gauss(x, y, 0.013, -0.020, 0.007, 0.0065) + _gauss(x, y, -0.013, -0.020, 0.007, 0.0065))
    return ridge + wings


def _face_relief(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Forward displacement of the facial features (before the front mask)."""
    ax = np.abs(x)
    sockets = -0.011 * _gauss(ax, y, EYE_X, EYE_Y, 0.018, 0.013)
    lids = 0.003 * (
        _gauss(ax, y, EYE_X, EYE_Y + 0.0085, 0.012, 0.004) + _gauss(ax, y, EYE_X, EYE_Y - 0.008, 0.011, 0.0035)
    )
    brow = 0.0045 * _gauss(ax, y, 0.028, 0.037, 0.022, 0.0065)
    cheeks = 0.004 * _gauss(ax, y, 0.045, -0.008, 0.016, 0.016)
    lip_x = np.exp(-((x / 0.021) ** 4))
    upper_lip = 0.0045 * lip_x * np.exp(-(((y - MOUTH_Y - 0.0045) / 0.0045) ** 2))
    lower_lip = 0.0050 * lip_x * np.exp(-(((y - MOUTH_Y + 0.0055) / 0.0045) ** 2))
    lip_line = -0.0015 * lip_x * np.exp(-(((y - MOUTH_Y) / 0.0015) ** 2))
    sulcus = -0.002 * _gauss(x, y, 0.0, MOUTH_Y - 0.017, 0.018, 0.004)
    chin = 0.006 * _gauss(x, y, 0.0, -0.074, 0.017, 0.010)
    return _nose(x, y) + sockets + lids + brow + cheeks + upper_lip + lower_lip + lip_line + sulcus + chin


def _ears(y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Sideways displacement of the ears (before the side mask)."""
    return 0.011 * _gauss(y, z, -0.002, -0.014, 0.017, 0.011)


@dataclass
class _Skin:
    """The head surface: positions, faces and the per-vertex data the weights and bases are built from."""

    positions: np.ndarray  # [S, 3]
    faces: np.ndarray  # [Fs, 3]
    front: np.ndarray  # [S] 0 at the sides/back, 1 facing forward
    azimuth: np.ndarray  # [S]
    ring: np.ndarray  # [S] ring (row) index, -1 for the crown pole; the lower-lip copies count as row r_m + 1
    lower_side: np.ndarray  # [S] 1 below the lip line (lower-lip copies included), 0 on or above it
    cut: np.ndarray  # [S] 1 in the columns well inside the mouth cut, falling to 0 at the corners
    lip_rows: tuple[np.ndarray, np.ndarray]  # upper / lower lip seam rows [n], corners shared
    grid_faces: int = -1  # faces [:grid_faces] are the ring grid's, in _grid_faces order; the neck cap's follow


def _build_skin() -> _Skin:
    """Ring grid around the profile with a crown pole, sculpted, and cut open along the lip line."""
    rows = _profile_rows()
    phi = _azimuths()
    sin, cos = np.sin(phi)[None, :], np.cos(phi)[None, :]
    depth = np.where(cos >= 0.0, rows[:, 2:3], rows[:, 3:4])  # [R, C]
    x = rows[:, 1:2] * sin
    y = np.broadcast_to(rows[:, 0:1], x.shape)
    z = depth * cos
    front = _smoothstep(0.0, 0.55, cos) * np.ones_like(x)
    side = _smoothstep(0.55, 0.95, np.abs(sin)) * (np.abs(cos) < 0.6)
    z = z + front * _face_relief(x, y)
    x = x + np.sign(x) * side * _ears(y, z)
    n_rows = rows.shape[0]
    crown = np.array([[0.0, _profile_keys()[0, 0], 0.0]])
    grid = np.stack([x, y, z], -1).reshape(-1, 3)
    skin = _cut_mouth(
        np.concatenate([crown, grid]),
        _grid_faces(n_rows),
        np.concatenate([[0.0], front.reshape(-1)]),
        np.concatenate([[0.0], np.broadcast_to(phi, x.shape).reshape(-1)]),
        n_rows,
    )
    return _close_neck(skin, n_rows)


def _close_neck(skin: _Skin, n_rows: int) -> _Skin:
    """Close the neck's open base ring with a fan to its centre, so the surface has no hole to see inside through
    (only the mouth, closed behind by the mouth pocket of `add_teeth`)."""
    ring = _grid_index(n_rows - 1, np.arange(N_COLUMNS))
    pole = len(skin.positions)
    centre = skin.positions[ring].mean(0, keepdims=True)
    c = np.arange(N_COLUMNS)
    fan = np.stack([np.full(N_COLUMNS, pole), _grid_index(n_rows - 1, c + 1), _grid_index(n_rows - 1, c)], 1)
    return replace(
        skin,
        positions=np.concatenate([skin.positions, centre]),
        faces=np.concatenate([skin.faces, fan]).astype(np.int64),
        front=np.append(skin.front, 0.0),
        azimuth=np.append(skin.azimuth, 0.0),
        ring=np.append(skin.ring, -1),  # like the crown pole: no ring of its own
        lower_side=np.append(skin.lower_side, 1.0),
        cut=np.append(skin.cut, 0.0),
        grid_faces=len(skin.faces),
    )


def _grid_index(r: np.ndarray | int, c: np.ndarray | int) -> np.ndarray:
    return 1 + np.asarray(r) * N_COLUMNS + np.asarray(c) % N_COLUMNS


def _grid_faces(n_rows: int) -> np.ndarray:
    """Crown fan plus two outward-facing triangles per grid quad [F, 3]."""
    c = np.arange(N_COLUMNS)
    fan = np.stack([np.zeros(N_COLUMNS, np.int64), _grid_index(0, c), _grid_index(0, c + 1)], 1)
    r, c = np.meshgrid(np.arange(n_rows - 1), c, indexing="ij")
    r, c = r.reshape(-1), c.reshape(-1)
    a, b = _grid_index(r, c), _grid_index(r, c + 1)
    d, e = _grid_index(r + 1, c), _grid_index(r + 1, c + 1)
    return np.concatenate([fan, np.stack([a, e, b], 1), np.stack([a, d, e], 1)]).astype(np.int64)


def _cut_mouth(positions: np.ndarray, faces: np.ndarray, front: np.ndarray, azimuth: np.ndarray, n_rows: int) -> _Skin:
    """Duplicate the lip-line vertices between the corners; faces below the line use the copies."""
    row = np.concatenate([[-1], np.arange(n_rows * N_COLUMNS) // N_COLUMNS])  # ring of every vertex
    r_m = int(np.argmin(np.abs(positions[_grid_index(np.arange(n_rows), 0), 1] - MOUTH_Y)))
    ring = _grid_index(r_m, np.arange(N_COLUMNS))
    cols = np.flatnonzero((np.abs(positions[ring, 0]) < MOUTH_HALF_WIDTH) & (positions[ring, 2] > 0))
    seam = ring[cols]  # consecutive front columns, ordered -x to +x
    copies = positions.shape[0] + np.arange(seam.size)
    lookup = np.arange(positions.shape[0])
    lookup[seam] = copies
    below = row[faces].max(1) > r_m  # faces of the lower lip band (and everything under it)
    faces = np.where(below[:, None], lookup[faces], faces)
    corners = ring[[cols[0] - 1, cols[-1] + 1]]
    row = np.concatenate([row, np.full(seam.size, r_m + 1)])  # the copies belong to the lower side
    col = np.concatenate([[-1], np.arange(n_rows * N_COLUMNS) % N_COLUMNS, cols])
    all_pos = np.concatenate([positions, positions[seam]])
    cut = _smoothstep(MOUTH_HALF_WIDTH, 0.6 * MOUTH_HALF_WIDTH, np.abs(all_pos[:, 0])) * np.isin(col, cols)
    return _Skin(
        positions=all_pos,
        faces=faces.astype(np.int64),
        front=np.concatenate([front, front[seam]]),
        azimuth=np.concatenate([azimuth, azimuth[seam]]),
        ring=row,
        lower_side=(row > r_m).astype(np.float64),
        cut=cut,
        lip_rows=(
            np.concatenate([corners[:1], seam, corners[1:]]).astype(np.int64),
            np.concatenate([corners[:1], copies, corners[1:]]).astype(np.int64),
        ),
    )


# ------------------------------------------------------------------------------------------------- eyes


@dataclass
class _Eye:
    """One eyeball: a sphere looking toward +z, its centre, faces (local indices) and their regions."""

    center: np.ndarray  # [3]
    positions: np.ndarray  # [E, 3]; vertex 0 is the front pole, vertex E-1 the back pole
    faces: np.ndarray  # [Fe, 3]
    regions: np.ndarray  # [Fe]


def _eyeball(sign: float, skin: _Skin) -> _Eye:
    """Eyeball in the socket at x = sign * EYE_X, its front pole EYE_PROTRUSION in front of the socket skin."""
    x = sign * EYE_X
    gap = np.hypot(skin.positions[:, 0] - x, skin.positions[:, 1] - EYE_Y) + (skin.front < 0.5)
    z_skin = skin.positions[np.argmin(gap), 2]
    center = np.array([x, EYE_Y, z_skin + EYE_PROTRUSION - EYE_RADIUS])
    polar = np.array([0.2, IRIS_ANGLE, 0.62, 0.85, 1.1, 1.4, 1.7, 2.0, 2.35, 2.75])  # denser at the iris
    n_seg = 16
    az = 2.0 * np.pi * np.arange(n_seg) / n_seg
    ring_dirs = np.stack(
        [np.sin(polar)[:, None] * np.cos(az), np.sin(polar)[:, None] * np.sin(az), np.cos(polar)[:, None] + 0 * az],
        -1,
    ).reshape(-1, 3)
    dirs = np.concatenate([[[0.0, 0.0, 1.0]], ring_dirs, [[0.0, 0.0, -1.0]]])
    faces = _sphere_faces(len(polar), n_seg)
    faces = _orient_outward(faces, dirs, np.zeros(3))
    centroid_polar = np.arccos(np.clip(_unit(dirs[faces].mean(1))[:, 2], -1.0, 1.0))
    regions = np.where(centroid_polar < IRIS_ANGLE, IRIS, EYE_WHITE).astype(np.int64)
    return _Eye(center=center, positions=center + EYE_RADIUS * dirs, faces=faces, regions=regions)


def _sphere_faces(n_rings: int, n_seg: int) -> np.ndarray:
    """UV-sphere triangles: front fan, quads between rings, back fan (vertex 0 front pole, last back pole)."""
    ring = lambda r, s: 1 + r * n_seg + s % n_seg  # noqa: E731
    s = np.arange(n_seg)
    back = 1 + n_rings * n_seg
    tris = [np.stack([np.zeros(n_seg, np.int64), ring(0, s), ring(0, s + 1)], 1)]
    for r in range(n_rings - 1):
        tris.append(np.stack([ring(r, s), ring(r + 1, s), ring(r + 1, s + 1)], 1))
        tris.append(np.stack([ring(r, s), ring(r + 1, s + 1), ring(r, s + 1)], 1))
    tris.append(np.stack([np.full(n_seg, back), ring(n_rings - 1, s + 1), ring(n_rings - 1, s)], 1))
    return np.concatenate(tris).astype(np.int64)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _orient_outward(faces: np.ndarray, positions: np.ndarray, center: np.ndarray) -> np.ndarray:
    """Flip each triangle whose normal points toward `center` (for convex pieces such as the eyeballs)."""
    p = positions[faces]
    normals = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    inward = np.einsum("fc,fc->f", normals, p.mean(1) - center) < 0
    return np.where(inward[:, None], faces[:, ::-1], faces)


# ---------------------------------------------------------------------------------------------- regions


def _hairline(azimuth: np.ndarray) -> np.ndarray:
    """Height of the hairline around the head: high on the forehead, above the ears, low at the nape."""
    knots = [0.0, 0.6, 1.0, 1.3, 1.55, 1.85, 2.2, np.pi]
    heights = [0.068, 0.064, 0.055, 0.040, 0.030, 0.026, -0.020, -0.055]
    return np.interp(np.abs(azimuth), knots, heights)


def _label_points(skin: _Skin) -> np.ndarray:
    """Where each skin face is classified [F, 3]: its grid quad's centre, so both halves of a quad agree."""
    p = skin.positions[skin.faces]  # [F, 3, 3]; faces in _grid_faces order: fan, (a, e, b) block, (a, d, e) block
    grid = len(p) if skin.grid_faces < 0 else skin.grid_faces
    n_quads = (grid - N_COLUMNS) // 2
    fan = p[:N_COLUMNS].mean(1)
    first = 0.5 * (p[N_COLUMNS : N_COLUMNS + n_quads, 0] + p[N_COLUMNS : N_COLUMNS + n_quads, 1])
    second = 0.5 * (p[N_COLUMNS + n_quads : grid, 0] + p[N_COLUMNS + n_quads : grid, 2])
    neck_cap = p[grid:].mean(1)
    return np.concatenate([fan, first, second, neck_cap])


def _skin_regions(skin: _Skin) -> np.ndarray:
    """Region label per skin face from its quad centre: hair above the hairline, brows, lips, else skin."""
    c = _label_points(skin)  # [F, 3]
    x, y = c[:, 0], c[:, 1]
    front = skin.front[skin.faces].min(1)
    regions = np.full(len(c), SKIN, dtype=np.int64)
    regions[y > _hairline(np.arctan2(x, c[:, 2]))] = HAIR
    t = (np.abs(x) - 0.031) / 0.022  # -1..1 along each brow
    brow_y = 0.040 + 0.005 * (1.0 - t**2)
    regions[(front > 0.5) & (np.abs(t) < 1.0) & (np.abs(y - brow_y) < 0.0045 * (1.0 - 0.4 * t**2))] = BROWS
    u = np.clip(1.0 - (x / (MOUTH_HALF_WIDTH + 0.002)) ** 2, 0.0, None)
    upper = (y > MOUTH_Y) & (y < MOUTH_Y + 0.0095 * np.sqrt(u) - 0.0015 * np.exp(-((x / 0.004) ** 2)))
    lower = (y < MOUTH_Y) & (y > MOUTH_Y - 0.0105 * np.sqrt(u))
    regions[(front > 0.5) & (u > 0.0) & (upper | lower)] = LIPS
    return regions


# ----------------------------------------------------------------------------------------- whole mesh


@dataclass
class _Mesh:
    """Skin + eyeballs, with the per-vertex data the weights and bases are computed from."""

    positions: np.ndarray  # [V, 3]
    faces: np.ndarray  # [F, 3]
    regions: np.ndarray  # [F]
    proxy: np.ndarray  # [V, 3] where smooth fields are sampled: eyeball vertices use their eye centre (rigid)
    part: np.ndarray  # [V] 0 skin, 1 left eyeball, 2 right eyeball
    skin: _Skin
    eye_poles: list[tuple[int, int]]  # (front pole, back pole) vertex of each eyeball; their mean is the centre


def _assemble(skin: _Skin, eyes: list[_Eye]) -> _Mesh:
    """Concatenate the skin and the eyeballs into one mesh."""
    positions, faces, regions, proxy, part = (
        [skin.positions],
        [skin.faces],
        [_skin_regions(skin)],
        [skin.positions],
        [np.zeros(len(skin.positions), np.int64)],
    )
    poles = []
    offset = len(skin.positions)
    for i, eye in enumerate(eyes):
        positions.append(eye.positions)
        faces.append(eye.faces + offset)
        regions.append(eye.regions)
        proxy.append(np.broadcast_to(eye.center, eye.positions.shape))
        part.append(np.full(len(eye.positions), i + 1, np.int64))
        poles.append((offset, offset + len(eye.positions) - 1))
        offset += len(eye.positions)
    return _Mesh(
        positions=np.concatenate(positions),
        faces=np.concatenate(faces).astype(np.int64),
        regions=np.concatenate(regions).astype(np.int64),
        proxy=np.concatenate(proxy),
        part=np.concatenate(part),
        skin=skin,
        eye_poles=poles,
    )


# ----------------------------------------------------------------------------------- skinning and joints


def _skin_attr(mesh: _Mesh, values: np.ndarray, eye_value: float) -> np.ndarray:
    """A per-skin-vertex array extended to all vertices (eyeballs get `eye_value`) [V]."""
    return np.concatenate([values, np.full(len(mesh.positions) - len(values), eye_value)])


def _lower_face(mesh: _Mesh) -> np.ndarray:
    """How much a vertex belongs below the lip line: 0/1 across the cut, a smooth 0..1 ramp elsewhere [V]."""
    skin = mesh.skin
    ramp = _smoothstep(MOUTH_Y + 0.015, MOUTH_Y - 0.015, skin.positions[:, 1])
    return _skin_attr(mesh, skin.cut * skin.lower_side + (1.0 - skin.cut) * ramp, 0.0)


def _jaw_weight(mesh: _Mesh) -> np.ndarray:
    """Jaw skinning weight: the lower face and chin, fading toward the ears and down the neck [V]."""
    skin = mesh.skin
    lateral = _smoothstep(1.45, 0.85, np.abs(skin.azimuth))
    neck = _smoothstep(-0.125, -0.092, skin.positions[:, 1])
    return _lower_face(mesh) * _skin_attr(mesh, lateral * neck, 0.0)


def _lbs_weights(mesh: _Mesh) -> np.ndarray:
    """Per-vertex weights [V, 5] over (global, neck, jaw, left_eye, right_eye); rows sum to 1."""
    jaw = _jaw_weight(mesh)
    base = _smoothstep(-0.115, -0.155, mesh.positions[:, 1])  # neck base follows the global joint
    skin = (mesh.part == 0).astype(np.float64)
    weights = np.stack(
        [
            skin * base * (1.0 - jaw),
            skin * (1.0 - base) * (1.0 - jaw),
            jaw,
            (mesh.part == 1).astype(np.float64),
            (mesh.part == 2).astype(np.float64),
        ],
        1,
    )
    return weights / weights.sum(1, keepdims=True)


def _joint_regressor(mesh: _Mesh) -> np.ndarray:
    """J_regressor [5, V]: each joint a convex combination of vertices (rings, hinge points, eye poles)."""
    skin = mesh.skin
    n_rows = int(skin.ring.max())  # the lower-lip copies count as a ring below r_m, so max is the last row
    reg = np.zeros((5, len(mesh.positions)))
    last = np.flatnonzero(skin.ring == n_rows)
    reg[0, last] = 1.0 / len(last)  # global: centre of the neck base ring
    ring_y = np.array([skin.positions[skin.ring == r, 1].mean() for r in range(n_rows + 1)])
    neck = np.flatnonzero(skin.ring == int(np.argmin(np.abs(ring_y - NECK_JOINT_Y))))
    reg[1, neck] = 1.0 / len(neck)  # neck: centre of the ring at the top of the neck
    for sign in (1.0, -1.0):  # jaw: midpoint of the skin points nearest the two jaw hinges
        target = np.array([sign * JAW_HINGE[0], JAW_HINGE[1], JAW_HINGE[2]])
        reg[2, np.argmin(np.linalg.norm(skin.positions - target, axis=1))] += 0.5
    for j, (front, back) in enumerate(mesh.eye_poles):
        reg[3 + j, [front, back]] = 0.5  # eyes: the eyeball centre
    return reg


# ---------------------------------------------------------------------------------------------- bases


def _normalized(field: np.ndarray, amplitude_mm: float) -> np.ndarray:
    """Scale a displacement field [V, 3] so its largest vertex displacement is amplitude_mm."""
    peak = np.linalg.norm(field, axis=1).max()
    return field * (amplitude_mm * 1e-3 / peak) if peak > 0 else field


def _wave_field(rng: np.random.Generator, p: np.ndarray, wavelength: float) -> np.ndarray:
    """Smooth random displacement [V, 3]: a few random plane waves per component."""
    field = np.zeros_like(p)
    for comp in range(3):
        for _ in range(3):
            direction = _unit(rng.normal(size=3))
            k = 2.0 * np.pi / wavelength * rng.uniform(0.7, 1.3)
            field[:, comp] += rng.normal() * np.sin(k * (p @ direction) + rng.uniform(0.0, 2.0 * np.pi))
    return field


def _bump_field(rng: np.random.Generator, p: np.ndarray, centers: np.ndarray) -> np.ndarray:
    """Smooth localised displacement [V, 3]: two Gaussian bumps with random centres and directions."""
    field = np.zeros_like(p)
    for _ in range(2):
        c = centers[rng.integers(len(centers))]
        sigma = rng.uniform(0.012, 0.025)
        falloff = np.exp(-np.sum((p - c) ** 2, axis=1) / (2.0 * sigma**2))
        field += falloff[:, None] * _unit(rng.normal(size=3))
    return field


def _shapedirs(mesh: _Mesh, n_shape: int, rng: np.random.Generator) -> np.ndarray:
    """Identity shape basis [V, 3, n_shape]: smooth global deformations, eyeballs moved rigidly."""
    p = mesh.proxy
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    front = _skin_attr(mesh, mesh.skin.front, 1.0)
    zero = np.zeros_like(x)
    lower = _smoothstep(-0.02, -0.07, y)
    named = [
        np.stack([x, zero, zero], 1),  # width
        np.stack([zero, y, zero], 1),  # height
        np.stack([zero, zero, z], 1),  # depth
        np.stack([x * lower, zero, zero], 1),  # jaw width
        np.stack([zero, zero, front * _nose(x, y)], 1),  # nose size
        np.stack([zero, -0.4 * front, front], 1) * _gauss(x, y, 0.0, -0.074, 0.02, 0.014)[:, None],  # chin
        np.stack([zero, zero, front], 1) * _gauss(x, y, 0.0, 0.065, 0.04, 0.02)[:, None],  # forehead
        np.stack([np.sign(x) * front, zero, zero], 1) * _gauss(np.abs(x), y, 0.045, -0.01, 0.02, 0.02)[:, None],
    ]
    fields = [_normalized(f, SHAPE_SIGMA_MM) for f in named]
    while len(fields) < n_shape:
        fields.append(_normalized(_wave_field(rng, p, 0.2), SHAPE_SIGMA_MM))
    return np.stack(fields[:n_shape], 2) if n_shape else np.zeros((len(p), 3, 0))


# Named expression fields, in basis order (coefficient k moves field k); coefficients past these are random local
# bumps. docs/demo-speaker.md tabulates them with the motion signals that drive them.
EXPRESSION_FIELDS = (
    "mouth_open", "smile", "pucker", "funnel", "lip_press", "upper_lip_raise", "lower_lip_depress",
    "mouth_stretch", "corner_down", "chin_raise", "cheek_raise", "brow_raise", "brow_furrow", "blink_left",
    "blink_right",
)  # fmt: skip
# The random bumps drawn for a basis of n_expr fields: as many as when only 4 fields were named, so the bases built
# after the expression basis (pose correctives) keep their random draws whatever the number of named fields.
_LEGACY_NAMED_FIELDS = 4


def _blink_field(mesh: _Mesh, sign: float) -> np.ndarray:
    """Eye closure [V, 3] of the eye at x = sign * EYE_X: the upper lid sweeps down and a little forward over the
    eyeball (forward so its skin passes in front of the eyeball, not through it), the lower lid rises a little."""
    p = mesh.positions
    front = _skin_attr(mesh, mesh.skin.front, 0.0)
    dx, dy = p[:, 0] - sign * EYE_X, p[:, 1] - EYE_Y
    across = front * np.exp(-((dx / 0.019) ** 4))  # flat over the eye's width, gone at the nose and temple
    upper = _smoothstep(-0.004, 0.0, dy) * (1.0 - _smoothstep(0.006, 0.022, dy))  # lid: full, fading to the brow
    lower = np.exp(-(((dy + 0.008) / 0.004) ** 2))  # the lower lid's row
    return across[:, None] * np.stack(
        [np.zeros_like(dx), -upper + 0.6 * lower, 0.35 * upper + 0.1 * lower], 1
    )


def _exprdirs(mesh: _Mesh, n_expr: int, rng: np.random.Generator) -> np.ndarray:
    """Expression basis [V, 3, n_expr]: the local action fields of EXPRESSION_FIELDS, then random local bumps.

    Each field is scaled so its largest vertex displacement is EXPR_SIGMA_MM per unit coefficient; eyeballs get
    no expression (they move with the eye joints only).
    """
    p = mesh.positions
    x, y = p[:, 0], p[:, 1]
    ax, sx = np.abs(x), np.sign(x)
    front = _skin_attr(mesh, mesh.skin.front, 0.0)  # eyeballs get no expression
    zero = np.zeros_like(x)
    lower = _lower_face(mesh)  # 1 on the lower lip and below, 0 on the upper lip and above (0/1 across the cut)
    side = 2.0 * lower - 1.0  # +1 lower lip, -1 upper lip, 0 at the corners
    around_mouth = front * _gauss(x, y, 0.0, MOUTH_Y, 0.028, 0.02)
    open_dy = np.where(side > 0, -side, -0.4 * side) * around_mouth
    corners = front * (
        _gauss(x, y, MOUTH_HALF_WIDTH, MOUTH_Y, 0.012, 0.012) - _gauss(x, y, -MOUTH_HALF_WIDTH, MOUTH_Y, 0.012, 0.012)
    )  # signed: +right corner region (x > 0), - left
    corner = np.abs(corners)
    pucker = front * _gauss(x, y, 0.0, MOUTH_Y, 0.026, 0.014)
    lips = front * _gauss(x, y, 0.0, MOUTH_Y, 0.022, 0.009)  # both lips, to the corners
    upper_lip = (1.0 - lower) * front * _gauss(x, y, 0.0, MOUTH_Y + 0.006, 0.02, 0.008)
    lower_lip = lower * front * _gauss(x, y, 0.0, MOUTH_Y - 0.007, 0.02, 0.009)
    chin = front * _gauss(x, y, 0.0, -0.072, 0.02, 0.014)
    cheeks = front * _gauss(ax, y, 0.042, -0.008, 0.016, 0.013)
    brows = front * _gauss(ax, y, 0.03, 0.04, 0.025, 0.014)
    inner_brows = front * _gauss(ax, y, 0.014, 0.036, 0.013, 0.01)
    named = {
        "mouth_open": np.stack([zero, open_dy, -0.15 * np.clip(side, 0, None) * around_mouth], 1),
        "smile": np.stack([0.6 * corners, corner, -0.4 * corner], 1),  # corners up, out and back
        "pucker": np.stack([-x / MOUTH_HALF_WIDTH * pucker, zero, pucker], 1),  # lips narrow and push forward
        "funnel": np.stack([zero, -0.7 * side * lips, lips], 1),  # lips flare apart and forward
        "lip_press": np.stack([zero, -(y - MOUTH_Y) / 0.009 * lips, -0.6 * lips], 1),  # lips thin and roll in
        "upper_lip_raise": np.stack([zero, upper_lip, 0.3 * upper_lip], 1),
        "lower_lip_depress": np.stack([zero, -lower_lip, 0.2 * lower_lip], 1),
        "mouth_stretch": np.stack([sx * corner, -0.3 * corner, -0.2 * corner], 1),  # corners pulled sideways
        "corner_down": np.stack([0.2 * corners, -corner, zero], 1),
        "chin_raise": np.stack([zero, 0.7 * chin + 0.3 * lower_lip, 0.6 * chin], 1),  # chin boss up, lower lip pushed
        "cheek_raise": np.stack([0.2 * sx * cheeks, cheeks, 0.3 * cheeks], 1),
        "brow_raise": np.stack([zero, brows, zero], 1),
        "brow_furrow": np.stack([-0.6 * sx * inner_brows, -inner_brows, 0.2 * inner_brows], 1),  # inner brows down, in
        "blink_left": _blink_field(mesh, 1.0),  # FLAME's left eye: the subject's left, +x
        "blink_right": _blink_field(mesh, -1.0),
    }
    assert tuple(named) == EXPRESSION_FIELDS
    fields = [_normalized(named[name], EXPR_SIGMA_MM) for name in EXPRESSION_FIELDS[:n_expr]]
    skin = mesh.part == 0
    face = skin & (np.abs(x) < 0.055) & (y > -0.09) & (y < 0.06) & (front > 0.7)
    centers = p[face]
    bumps = [_normalized(_bump_field(rng, p, centers) * skin[:, None], EXPR_SIGMA_MM)
             for _ in range(max(0, n_expr - _LEGACY_NAMED_FIELDS))]
    fields += bumps[: max(0, n_expr - len(fields))]
    return np.stack(fields, 2) if n_expr else np.zeros((len(p), 3, 0))


def _posedirs(mesh: _Mesh, weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Pose correctives [36, V*3]: small smooth fields near the neck and the jaw; eyeballs stay rigid."""
    p = mesh.positions
    skin = (mesh.part == 0).astype(np.float64)
    jaw = weights[:, 2]
    regions = [
        skin * np.exp(-(((p[:, 1] - NECK_JOINT_Y) / 0.03) ** 2)),  # neck: the throat and nape
        skin * 4.0 * jaw * (1.0 - jaw),  # jaw: where the skin stretches between the jaw and the head
    ]
    out = np.zeros((POSE_FEATURE_DIM, len(p), 3))
    for j, region in enumerate(regions):
        for f in range(9):
            out[9 * j + f] = _normalized(_wave_field(rng, p, 0.08) * region[:, None], POSE_CORRECTIVE_MM)
    return out.reshape(POSE_FEATURE_DIM, -1)
