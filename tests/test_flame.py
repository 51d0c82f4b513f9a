"""FLAME layer: LBS against an independent numpy FLAME, the npz loader, the teeth extension, the demo head, ONNX."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gaussiantalker.exporter.demo.procedural_head import (
    MOUTH_Y,
    REGION_COLORS,
    REGION_NAMES,
    demo_lip_vertices,
    make_demo_head,
)
from gaussiantalker.exporter.model.flame import FlameArrays
from gaussiantalker.exporter.model.flame_lbs import FlameLayer, lbs, rodrigues
from gaussiantalker.exporter.model.flame_npz import load_flame_npz
from gaussiantalker.exporter.model.flame_teeth import add_teeth
from gaussiantalker.sdk.config import FLAME_PARENTS, POSE_DIM
from gaussiantalker.sdk.errors import CheckpointError

JAW = slice(6, 9)  # pose triple of the jaw joint
NECK = slice(3, 6)


@pytest.fixture(scope="module")
def head() -> FlameArrays:
    return make_demo_head()


@pytest.fixture(scope="module")
def head_layer(head: FlameArrays) -> FlameLayer:
    return FlameLayer(head)


def _params(arrays: FlameArrays, batch: int = 1) -> tuple[torch.Tensor, ...]:
    """Zero (shape, expression, pose, translation) for `arrays`."""
    return (
        torch.zeros(batch, arrays.n_shape),
        torch.zeros(batch, arrays.n_expr),
        torch.zeros(batch, POSE_DIM),
        torch.zeros(batch, 3),
    )


def _run(layer: FlameLayer, shape, expression, pose, translation=None) -> np.ndarray:
    """Vertices [B, V, 3] as float64 numpy."""
    if translation is None:
        translation = torch.zeros(pose.shape[0], 3)
    with torch.no_grad():
        return layer(shape, expression, pose, translation).double().numpy()


# ------------------------------------------------------------------------------ independent numpy FLAME


def _np_rodrigues(rotvec: np.ndarray) -> np.ndarray:
    """Textbook Rodrigues in float64 [3] -> [3, 3] (exact identity at zero)."""
    angle = np.linalg.norm(rotvec)
    if angle < 1e-12:
        return np.eye(3)
    k = rotvec / angle
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


def _np_flame(vt, shapedirs, exprdirs, posedirs_v336, j_reg, weights, parents, beta, eps, pose):
    """FLAME in its original layouts (posedirs [V, 3, 36]) -> (vertices [V, 3], blended rotation [V, 3, 3])."""
    v = vt + np.einsum("vcl,l->vc", shapedirs, beta) + np.einsum("vcl,l->vc", exprdirs, eps)
    joints = j_reg @ v
    rots = [_np_rodrigues(r) for r in pose.reshape(-1, 3)]
    feature = np.concatenate([(r - np.eye(3)).reshape(-1) for r in rots[1:]])
    v = v + np.einsum("vck,k->vc", posedirs_v336, feature)
    world = []
    for i, rot in enumerate(rots):
        local = np.eye(4)
        local[:3, :3] = rot
        local[:3, 3] = joints[i] - (joints[parents[i]] if i else 0.0)
        world.append(local if i == 0 else world[parents[i]] @ local)
    skin = np.stack(world)
    skin[:, :3, 3] -= np.einsum("jab,jb->ja", skin[:, :3, :3], joints)
    blended = np.einsum("vj,jab->vab", weights, skin)
    out = np.einsum("vab,vb->va", blended[:, :3, :3], v) + blended[:, :3, 3]
    return out, blended[:, :3, :3]


def _np_flame_arrays(arrays: FlameArrays, beta, eps, pose):
    n_v = arrays.n_vertices
    return _np_flame(
        arrays.v_template.astype(np.float64),
        arrays.shapedirs.astype(np.float64),
        arrays.exprdirs.astype(np.float64),
        arrays.posedirs.T.reshape(n_v, 3, -1).astype(np.float64),
        arrays.J_regressor.astype(np.float64),
        arrays.lbs_weights.astype(np.float64),
        arrays.parents,
        beta,
        eps,
        pose,
    )


def _synthetic_flame_npz(path, n_v: int = 50, seed: int = 0) -> dict:
    """A small model in the exact key layout of a real FLAME npz (generic_model converted, dense J_regressor)."""
    rng = np.random.default_rng(seed)
    weights = rng.random((n_v, 5)) ** 3
    j_reg = rng.random((5, n_v))
    raw = {
        "v_template": rng.normal(scale=0.05, size=(n_v, 3)),
        "f": rng.integers(0, n_v, size=(80, 3)).astype(np.uint32),
        "shapedirs": rng.normal(scale=0.01, size=(n_v, 3, 400)),
        "posedirs": rng.normal(scale=0.01, size=(n_v, 3, 36)),
        "J_regressor": j_reg / j_reg.sum(1, keepdims=True),
        "weights": weights / weights.sum(1, keepdims=True),
        "kintree_table": np.array([[4294967295, 0, 1, 1, 1], [0, 1, 2, 3, 4]], dtype=np.int64),
    }
    np.savez(path, **raw)
    return raw


# --------------------------------------------------------------------------------------------------- (a)


def test_zero_parameters_give_the_template(head, head_layer):
    verts = _run(head_layer, *_params(head))
    np.testing.assert_allclose(verts[0], head.v_template, atol=1e-7)


def test_translation_is_added_after_lbs(head, head_layer):
    shape, expr, pose, _ = _params(head, 2)
    pose[:, JAW] = torch.tensor([0.2, 0.0, 0.0])
    offset = torch.tensor([[0.1, -0.2, 0.3], [0.0, 0.0, 0.0]])
    moved = _run(head_layer, shape, expr, pose, offset)
    still = _run(head_layer, shape, expr, pose)
    np.testing.assert_allclose(moved - still, offset.double().numpy()[:, None, :].repeat(head.n_vertices, 1), atol=1e-6)


# --------------------------------------------------------------------------------------------------- (b)


def test_npz_loader_matches_the_flame_formula(tmp_path):
    raw = _synthetic_flame_npz(tmp_path / "flame.npz")
    arrays = load_flame_npz(tmp_path / "flame.npz", n_shape=10, n_expr=7)
    assert arrays.parents == FLAME_PARENTS and arrays.faces.dtype == np.int64
    assert arrays.posedirs.shape == (36, 150) and arrays.exprdirs.shape == (50, 3, 7)
    layer = FlameLayer(arrays)
    rng = np.random.default_rng(1)
    for _ in range(3):
        beta, eps, pose = rng.normal(size=10), rng.normal(size=7), rng.normal(scale=0.5, size=15)
        expected, _ = _np_flame(
            raw["v_template"],
            raw["shapedirs"][:, :, :10],
            raw["shapedirs"][:, :, 300:307],
            raw["posedirs"],
            raw["J_regressor"],
            raw["weights"],
            FLAME_PARENTS,
            beta,
            eps,
            pose,
        )
        got = _run(layer, *(torch.tensor(a[None], dtype=torch.float32) for a in (beta, eps, pose)))
        np.testing.assert_allclose(got[0], expected, atol=2e-6)


def test_npz_loader_reports_missing_keys_and_refuses_pickles(tmp_path):
    raw = _synthetic_flame_npz(tmp_path / "full.npz")
    np.savez(tmp_path / "partial.npz", **{k: v for k, v in raw.items() if k != "posedirs"})
    with pytest.raises(CheckpointError, match="posedirs"):
        load_flame_npz(tmp_path / "partial.npz", 10, 10)
    np.savez(tmp_path / "pickled.npz", **{**raw, "v_template": np.array([{"evil": 1}], dtype=object)})
    with pytest.raises(CheckpointError, match="pickle|Object"):
        load_flame_npz(tmp_path / "pickled.npz", 10, 10)
    with pytest.raises(CheckpointError, match="expression"):
        load_flame_npz(tmp_path / "full.npz", 10, 101)
    np.save(tmp_path / "array.npy", raw["v_template"])
    (tmp_path / "corrupt.npz").write_bytes(b"PK\x03\x04 not really a zip")
    for bad in ("missing.npz", "array.npy", "corrupt.npz"):
        with pytest.raises(CheckpointError):
            load_flame_npz(tmp_path / bad, 10, 10)


def test_validate_names_the_bad_key(head):
    arrays = make_demo_head(n_shape=3, n_expr=3)
    arrays.posedirs = arrays.posedirs[:, :-3]
    with pytest.raises(CheckpointError, match="posedirs"):
        arrays.validate()
    again = FlameArrays.from_dict(head.to_dict())
    for key, value in head.to_dict().items():
        np.testing.assert_array_equal(np.asarray(getattr(again, key)), np.asarray(value))


# --------------------------------------------------------------------------------------------------- (c)


def test_teeth_copy_their_anchor_rows(head):
    anchors, teeth = head.teeth_anchors, np.arange(head.n_base_vertices, head.n_vertices)
    np.testing.assert_array_equal(head.shapedirs[teeth], head.shapedirs[anchors])
    np.testing.assert_array_equal(head.exprdirs[teeth], head.exprdirs[anchors])
    np.testing.assert_array_equal(head.lbs_weights[teeth], head.lbs_weights[anchors])
    pose_rows = head.posedirs.reshape(36, -1, 3)
    np.testing.assert_array_equal(pose_rows[:, teeth], pose_rows[:, anchors])
    assert not head.J_regressor[:, teeth].any()
    assert {REGION_NAMES[r] for r in head.regions[-(len(teeth) // 2) :]} <= {"teeth", "mouth_interior"}


def test_teeth_follow_their_anchor_lip_vertices(head, head_layer):
    anchors, teeth = head.teeth_anchors, np.arange(head.n_base_vertices, head.n_vertices)
    rng = np.random.default_rng(2)
    beta, eps = rng.normal(size=head.n_shape), rng.normal(size=head.n_expr)
    zero_pose = np.zeros(POSE_DIM)
    rest = _run(head_layer, *(torch.tensor(a[None], dtype=torch.float32) for a in (beta, eps, zero_pose)))[0]
    shift = rest - head.v_template  # without pose, teeth are displaced exactly like their anchors
    np.testing.assert_allclose(shift[teeth], shift[anchors], atol=1e-6)
    pose = np.zeros(POSE_DIM)
    pose[JAW], pose[NECK] = (0.3, 0.05, 0.0), (0.1, -0.2, 0.05)
    posed = _run(head_layer, *(torch.tensor(a[None], dtype=torch.float32) for a in (beta, eps, pose)))[0]
    _, blended = _np_flame_arrays(head, beta, eps, pose)
    offset = head.v_template[teeth].astype(np.float64) - head.v_template[anchors]  # the only per-tooth data
    expected = np.einsum("tab,tb->ta", blended[anchors], offset)  # the anchor's LBS transform, applied to it
    np.testing.assert_allclose(posed[teeth] - posed[anchors], expected, atol=2e-6)


def test_add_teeth_on_a_model_without_regions(tmp_path):
    _synthetic_flame_npz(tmp_path / "flame.npz")
    arrays = load_flame_npz(tmp_path / "flame.npz", 4, 4)
    with_teeth = add_teeth(arrays, [0, 1, 2, 3], [4, 5, 6, 7], depth=0.005, height=0.008)
    assert with_teeth.region_names == ("skin", "teeth", "mouth_interior")
    assert with_teeth.n_base_vertices == arrays.n_vertices
    assert (with_teeth.regions[: arrays.n_faces] == 0).all()
    assert set(with_teeth.regions[arrays.n_faces :].tolist()) == {1, 2}
    with pytest.raises(ValueError):
        add_teeth(arrays, [0, 1, 2], [4, 5], depth=0.005, height=0.008)


# --------------------------------------------------------------------------------------------------- (d)


def test_demo_head_structure(head):
    assert 3000 <= head.n_vertices <= 5000
    assert head.parents == FLAME_PARENTS and head.J_regressor.shape == (5, head.n_vertices)
    for key in ("v_template", "shapedirs", "exprdirs", "posedirs", "J_regressor", "lbs_weights"):
        assert np.isfinite(getattr(head, key)).all(), key
    assert head.faces.min() >= 0 and head.faces.max() < head.n_vertices
    tri = head.v_template[head.faces].astype(np.float64)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    assert area.min() > 1e-8  # m^2: no degenerate faces
    assert head.regions.shape == (head.n_faces,) and head.region_names == REGION_NAMES
    assert set(np.unique(head.regions).tolist()) == set(range(len(REGION_NAMES)))  # every region is used
    assert len(REGION_COLORS) == len(REGION_NAMES) and np.all(
        (np.array(REGION_COLORS) >= 0) & (np.array(REGION_COLORS) <= 1)
    )
    assert np.all(head.J_regressor >= 0) and np.allclose(head.J_regressor.sum(1), 1.0, atol=1e-5)


def test_demo_head_geometry(head):
    v = head.v_template
    assert 0.2 <= v[:, 1].max() - v[:, 1].min() <= 0.3 and np.abs(v.mean(0)).max() < 0.03
    nose = v[np.argmax(v[:, 2])]
    assert nose[2] > 0.09 and abs(nose[0]) < 1e-3  # the face looks toward +z, nose tip on the midline
    joints = head.J_regressor @ v
    upper, lower = demo_lip_vertices()
    lip = v[upper[len(upper) // 2]]
    assert joints[2, 1] > lip[1] and joints[2, 2] < lip[2] - 0.05  # jaw hinge above and behind the mouth
    assert joints[0, 1] < joints[1, 1] < joints[2, 1]  # neck base below the top of the neck below the jaw
    for j, sign in ((3, 1.0), (4, -1.0)):  # eye joints at the eyeball centres (left eye on +x)
        eyeball = np.flatnonzero(head.lbs_weights[:, j] > 0.5)
        np.testing.assert_allclose(joints[j], 0.5 * (v[eyeball].min(0) + v[eyeball].max(0)), atol=1e-4)
        assert np.sign(joints[j, 0]) == sign
    skin = np.isin(head.regions, [REGION_NAMES.index(n) for n in ("skin", "lips", "hair", "brows")])
    tri = v[head.faces[skin]].astype(np.float64)
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert (np.einsum("fc,fc->f", normals, tri.mean(1)) > 0).all()  # outward winding


def test_opening_the_jaw_opens_the_mouth(head, head_layer):
    shape, expr, pose, _ = _params(head)
    pose[0, JAW] = torch.tensor([0.3, 0.0, 0.0])
    posed = _run(head_layer, shape, expr, pose)[0]
    upper, lower = demo_lip_vertices()
    mid = len(upper) // 2
    assert abs(MOUTH_Y - head.v_template[upper[mid], 1]) < 1e-3
    moved = posed - head.v_template
    assert moved[lower[mid], 1] < -0.003  # lower lip down by more than 3 mm
    assert np.linalg.norm(moved[upper[mid]]) < 0.001  # upper lip stays
    edges = np.concatenate([head.faces[:, [0, 1]], head.faces[:, [1, 2]], head.faces[:, [2, 0]]])
    rest_len = np.linalg.norm(np.diff(head.v_template[edges], axis=1)[:, 0], axis=1)
    posed_len = np.linalg.norm(np.diff(posed[edges], axis=1)[:, 0], axis=1)
    assert (posed_len / rest_len).max() < 3.0  # stretched, not torn apart


def test_demo_expressions_are_meaningful(head, head_layer):
    upper, lower = demo_lip_vertices()
    mid = len(upper) // 2
    shape, expr, pose, _ = _params(head)
    expr[0, 0] = 1.0  # mouth open: lower lip down, upper lip up
    moved = _run(head_layer, shape, expr, pose)[0] - head.v_template
    assert moved[lower[mid], 1] < -0.002 and moved[upper[mid], 1] > 0.0005
    size = np.linalg.norm(head.exprdirs, axis=1).max(0)  # largest displacement of each 1-sigma basis
    assert np.all((size > 0.002) & (size < 0.005))
    a, b = make_demo_head(seed=0), make_demo_head(seed=1)
    np.testing.assert_array_equal(a.exprdirs, head.exprdirs)  # deterministic
    np.testing.assert_array_equal(a.v_template, b.v_template)
    assert not np.array_equal(a.exprdirs[:, :, 4:], b.exprdirs[:, :, 4:])  # the seed drives the random bases


# --------------------------------------------------------------------------------------------------- (e)


@pytest.mark.parametrize("angle", [0.0, np.pi, -np.pi, 10.0, -10.0, 1e-9])
def test_rodrigues_matches_numpy_at_extremes(angle):
    axes = np.array([[1.0, 0, 0], [0, 1.0, 0], [0.3, -0.5, 0.8]])
    rotvec = axes / np.linalg.norm(axes, axis=1, keepdims=True) * angle
    rot = rodrigues(torch.tensor(rotvec, dtype=torch.float32)).double().numpy()
    assert np.isfinite(rot).all()
    np.testing.assert_allclose(rot, np.stack([_np_rodrigues(r) for r in rotvec]), atol=2e-6)


@pytest.mark.parametrize("angle", [0.0, np.pi, -np.pi, 10.0, -10.0])
def test_lbs_is_finite_with_finite_gradients(head, head_layer, angle):
    shape, expr, _, translation = _params(head, 2)
    pose = torch.full((2, POSE_DIM), float(angle), requires_grad=True)
    verts = head_layer(shape, expr, pose, translation)
    assert torch.isfinite(verts).all()
    verts.square().sum().backward()
    assert torch.isfinite(pose.grad).all()


def test_rodrigues_gradient_at_zero_is_the_cross_matrix():
    rotvec = torch.zeros(1, 3, requires_grad=True)
    rodrigues(rotvec)[0, 2, 1].backward()  # R ~ I + [r]x, so dR[2, 1]/dr = (1, 0, 0)
    np.testing.assert_allclose(rotvec.grad.numpy(), [[1.0, 0.0, 0.0]], atol=1e-6)


def test_layer_is_deterministic(head, head_layer):
    rng = np.random.default_rng(3)
    args = [
        torch.tensor(rng.normal(size=(4, n)), dtype=torch.float32) for n in (head.n_shape, head.n_expr, POSE_DIM, 3)
    ]
    np.testing.assert_array_equal(_run(head_layer, *args[:3], args[3]), _run(head_layer, *args[:3], args[3]))


# --------------------------------------------------------------------------------------------------- (f)


class _LbsModule(torch.nn.Module):
    """`lbs` on fixed FLAME buffers, as the exporter would wrap it."""

    def __init__(self, arrays: FlameArrays) -> None:
        super().__init__()
        self.flame = FlameLayer(arrays)

    def forward(self, shape: torch.Tensor, expression: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
        f = self.flame
        verts, _ = lbs(
            f.v_template,
            f.shapedirs,
            f.exprdirs,
            f.posedirs,
            f.J_regressor,
            f.parents,
            f.lbs_weights,
            shape,
            expression,
            pose,
        )
        return verts


@pytest.mark.slow  # a torch.onnx export (~4 s); the quick run exports lbs inside the deform graph (test_graph_parity)
@pytest.mark.filterwarnings("ignore::UserWarning", "ignore::FutureWarning")
def test_lbs_exports_to_onnx_with_dynamic_batch(tmp_path):
    ort = pytest.importorskip("onnxruntime")
    pytest.importorskip("onnxscript")
    module = _LbsModule(make_demo_head(n_shape=8, n_expr=8)).eval()
    batch = torch.export.Dim("batch", min=1, max=64)
    example = (torch.zeros(2, 8), torch.zeros(2, 8), torch.zeros(2, POSE_DIM))
    path = tmp_path / "lbs.onnx"
    torch.onnx.export(
        module,
        example,
        str(path),
        dynamo=True,
        input_names=["shape", "expression", "pose"],
        output_names=["vertices"],
        dynamic_shapes={"shape": {0: batch}, "expression": {0: batch}, "pose": {0: batch}},
    )
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(4)
    for b in (1, 3):
        inputs = {
            "shape": rng.normal(size=(b, 8)).astype(np.float32),
            "expression": rng.normal(size=(b, 8)).astype(np.float32),
            "pose": rng.normal(scale=0.4, size=(b, POSE_DIM)).astype(np.float32),
        }
        (got,) = session.run(None, inputs)
        with torch.no_grad():
            want = module(*(torch.from_numpy(inputs[k]) for k in ("shape", "expression", "pose"))).numpy()
        assert got.shape == (b, module.flame.v_template.shape[0], 3)
        assert np.abs(got - want).max() < 1e-5
