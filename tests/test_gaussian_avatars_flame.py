"""GaussianAvatars' FLAME: the teeth extension (checked against an independent construction and against faces read
from GaussianAvatars' lists), static_offset folding, the model loader and its errors; and the test-side avatar
writer and numpy reference (tests/gaussian_avatars.py) themselves."""

from __future__ import annotations

import gaussian_avatars as ga
import numpy as np
import pytest
import torch
from flame_pickles import FlameSpec, flame_model, write_flame_pickle
from plyfile import PlyData

from gaussiantalker.exporter.imports.formats.flame_pkl import convert_flame_pkl
from gaussiantalker.exporter.imports.sources.gaussian_avatars_flame import (
    GA_N_EXPR,
    GA_N_SHAPE,
    GA_TEETH_VERTICES,
    LOWER_LIP_RING,
    UPPER_LIP_RING,
    add_gaussian_avatars_teeth,
    fold_static_offset,
    load_gaussian_avatars_flame,
    teeth_faces_local,
)
from gaussiantalker.exporter.model.flame_lbs import FlameLayer
from gaussiantalker.exporter.model.flame_npz import load_flame_npz
from gaussiantalker.exporter.model.flame_teeth import BASE_REGION, TEETH_REGION
from gaussiantalker.sdk.errors import CheckpointError, ImportFormatError

FULL = FlameSpec(n_vertices=5023, n_faces=9976)
# Faces copied from GaussianAvatars' f_teeth_upper / f_teeth_lower (local indices): each strip's first face, the
# face where the diagonal flips at the midline, and the last face.
UPPER_LITERAL = {0: [0, 31, 30], 13: [6, 7, 37], 14: [7, 8, 37], 27: [14, 44, 43], 28: [60, 75, 76],
                 42: [67, 82, 68], 56: [75, 30, 76], 83: [88, 44, 89]}
LOWER_LITERAL = {0: [45, 46, 15], 14: [52, 23, 22], 27: [58, 59, 29], 28: [90, 106, 105], 42: [97, 98, 112],
                 56: [105, 106, 45], 83: [118, 119, 59]}
UPPER_ROWS, LOWER_ROWS = ("UR", "UE", "URB", "UEB"), ("LR", "LE", "LRB", "LEB")


def _rows(names) -> np.ndarray:
    return np.concatenate([5023 + 15 * ga.TEETH_ROWS.index(n) + np.arange(15) for n in names])


@pytest.fixture(scope="module")
def model():
    return ga.synthetic_flame()


@pytest.fixture(scope="module")
def model_npz(model, tmp_path_factory):
    return ga.write_flame_npz(tmp_path_factory.mktemp("ga_flame") / "flame2023.npz", model)


@pytest.fixture(scope="module")
def flame(model_npz):
    return load_flame_npz(model_npz, GA_N_SHAPE, GA_N_EXPR)


@pytest.fixture(scope="module")
def teeth(flame):
    return add_gaussian_avatars_teeth(flame)


@pytest.fixture(scope="module")
def avatar(model, tmp_path_factory):
    return ga.write_gaussian_avatar(tmp_path_factory.mktemp("ga_avatar"), model)


# ------------------------------------------------------------------------------------------- teeth extension


def test_counts_and_flame_part_unchanged(flame, teeth):
    assert (teeth.n_vertices, teeth.n_faces, GA_TEETH_VERTICES) == (5143, 10144, 120)
    assert (teeth.n_shape, teeth.n_expr) == (300, 100)
    np.testing.assert_array_equal(teeth.v_template[:5023], flame.v_template)
    np.testing.assert_array_equal(teeth.faces[:9976], flame.faces)
    np.testing.assert_array_equal(teeth.shapedirs[:5023], flame.shapedirs)
    np.testing.assert_array_equal(teeth.exprdirs[:5023], flame.exprdirs)
    np.testing.assert_array_equal(teeth.posedirs[:, : 5023 * 3], flame.posedirs)
    np.testing.assert_array_equal(teeth.J_regressor[:, :5023], flame.J_regressor)
    np.testing.assert_array_equal(teeth.lbs_weights[:5023], flame.lbs_weights)
    assert teeth.v_template.dtype == np.float32 and teeth.faces.dtype == np.int64


def test_teeth_vertices_follow_the_rule(model, teeth):
    """Against the independent construction in tests/gaussian_avatars.py, and the rule's geometry directly."""
    np.testing.assert_allclose(teeth.v_template[5023:], ga.ga_teeth_vertices(model["v_template"]), rtol=0, atol=1e-7)
    v = teeth.v_template.astype(np.float64)
    upper, lower = v[list(UPPER_LIP_RING)], v[list(LOWER_LIP_RING)]
    d = np.linalg.norm(upper - lower, axis=1).mean()
    row = {name: v[_rows([name])] for name in ga.TEETH_ROWS}
    middle_xz = (upper + lower)[:, [0, 2]] / 2 - [0.0, 1.5 * d]
    mean_y = ((upper + lower) / 2)[:, 1].mean()
    tol = dict(rtol=0, atol=1e-7)
    np.testing.assert_allclose(row["UE"][:, [0, 2]], middle_xz, **tol)
    np.testing.assert_allclose(row["UE"][:, 1], mean_y + 0.1 * d, **tol)  # one straight bite line
    np.testing.assert_allclose(row["UR"] - row["UE"], np.tile([0.0, 2 * d, 0.0], (15, 1)), **tol)
    np.testing.assert_allclose(row["LE"] - row["UE"], np.tile([0.0, -0.2 * d, -0.4 * d], (15, 1)), **tol)
    np.testing.assert_allclose(row["LR"] - row["LE"], np.tile([0.0, -2 * d, 0.0], (15, 1)), **tol)
    for name in ("UR", "UE", "LR", "LE"):
        np.testing.assert_allclose(row[name + "B"] - row[name], np.tile([0.0, 0.0, -d], (15, 1)), **tol)
    assert 0.005 < d < 0.02  # the synthetic lips are about 1 cm apart: the rule is tested at a real scale


def test_teeth_faces_are_gaussian_avatars_lists(teeth):
    local = teeth.faces[9976:] - 5023
    np.testing.assert_array_equal(local, teeth_faces_local())
    np.testing.assert_array_equal(local, ga.ga_teeth_faces())  # the strip rule written independently
    for index, face in UPPER_LITERAL.items():
        assert local[index].tolist() == face, index
    for index, face in LOWER_LITERAL.items():
        assert local[84 + index].tolist() == face, index
    assert sorted(set(local[:84].ravel())) == sorted(_rows(UPPER_ROWS) - 5023)  # upper faces use upper rows only
    assert sorted(set(local[84:].ravel())) == sorted(_rows(LOWER_ROWS) - 5023)
    assert all(len(set(face)) == 3 for face in local.tolist())


def test_teeth_bases_skinning_and_regions(flame, teeth):
    lip_mean = (flame.shapedirs[list(UPPER_LIP_RING)].astype(np.float64) + flame.shapedirs[list(LOWER_LIP_RING)]) / 2
    for r in range(8):
        np.testing.assert_allclose(teeth.shapedirs[5023 + 15 * r: 5038 + 15 * r], lip_mean, rtol=0, atol=1e-9)
    assert np.abs(lip_mean).max() > 1e-4  # the shape dirs are not trivially zero
    assert not teeth.exprdirs[5023:].any()
    assert not teeth.posedirs[:, 5023 * 3:].any()
    assert not teeth.J_regressor[:, 5023:].any()
    np.testing.assert_array_equal(teeth.lbs_weights[_rows(UPPER_ROWS)], np.tile(np.eye(5)[1], (60, 1)))
    np.testing.assert_array_equal(teeth.lbs_weights[_rows(LOWER_ROWS)], np.tile(np.eye(5)[2], (60, 1)))
    assert teeth.region_names == (BASE_REGION, TEETH_REGION)
    names = np.asarray(teeth.region_names)[teeth.regions]
    assert (names[:9976] == BASE_REGION).all() and (names[9976:] == TEETH_REGION).all()
    assert teeth.teeth_anchors.size == 0 and teeth.n_base_vertices == 5143


def test_static_offset_folding_matches_gaussian_avatars_forward(model, teeth, avatar):
    """Folded into the template, static_offset gives GaussianAvatars' FLAME (numpy reference) for posed frames."""
    params = avatar["params"]
    folded = fold_static_offset(teeth, params["static_offset"])
    np.testing.assert_allclose(folded.v_template, teeth.v_template + params["static_offset"][0], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(fold_static_offset(teeth, params["static_offset"][0]).v_template, folded.v_template)
    layer = FlameLayer(folded)
    reference = ga.ga_flame_with_teeth(model)
    for frame in (0, len(params["expr"]) - 1):
        pose = ga.ga_pose(params, frame).reshape(1, 15)
        got = layer(torch.from_numpy(params["shape"][None]), torch.from_numpy(params["expr"][[frame]]),
                     torch.from_numpy(pose.astype(np.float32)), torch.from_numpy(params["translation"][[frame]]))
        want = ga.ga_flame_vertices(reference, params, frame)
        np.testing.assert_allclose(got[0].numpy(), want, rtol=0, atol=2e-6)
    last = len(params["expr"]) - 1
    moved = ga.ga_flame_vertices(reference, params, last) - ga.ga_flame_vertices(reference, params, 0)
    assert np.linalg.norm(moved, axis=1).max() > 0.01  # the clip moves the head by centimetres


@pytest.mark.parametrize("shape", [(5143,), (2, 5143, 3), (1, 5023, 3), (5143, 2)])
def test_static_offset_wrong_shape(teeth, shape):
    with pytest.raises(ImportFormatError, match=r"'static_offset' has shape .*expected \[1, 5143, 3\] or \[5143, 3\]"):
        fold_static_offset(teeth, np.zeros(shape, np.float32))
    with pytest.raises(ImportFormatError, match="static_offset"):
        fold_static_offset(teeth, np.full((5143, 3), np.nan, np.float32))


# ------------------------------------------------------------------------------------------------- loader


def test_loader_npz(model_npz, teeth):
    loaded = load_gaussian_avatars_flame(model_npz)
    for key in ("v_template", "shapedirs", "exprdirs", "posedirs", "J_regressor", "lbs_weights", "faces", "regions"):
        np.testing.assert_array_equal(getattr(loaded, key), getattr(teeth, key), err_msg=key)


def test_loader_pickle_and_gt_import_npz(tmp_path):
    pkl = tmp_path / "flame2023.pkl"
    arrays = write_flame_pickle(pkl, FULL)
    expected = add_gaussian_avatars_teeth(load_flame_npz(ga.write_flame_npz(tmp_path / "plain.npz", arrays), 300, 100))
    from_pickle = load_gaussian_avatars_flame(pkl)
    converted = convert_flame_pkl(pkl, tmp_path / "flame.npz")
    assert converted.version == "2023"
    from_npz = load_gaussian_avatars_flame(tmp_path / "flame.npz")
    for loaded in (from_pickle, from_npz):
        assert (loaded.n_vertices, loaded.n_faces) == (5143, 10144)
        for key in ("v_template", "shapedirs", "exprdirs", "posedirs", "J_regressor", "lbs_weights", "faces"):
            np.testing.assert_array_equal(getattr(loaded, key), getattr(expected, key), err_msg=key)
    convert_flame_pkl(pkl, tmp_path / "old.npz", version="2020")
    with pytest.raises(ImportFormatError, match=r"'flame_version' is '2020': GaussianAvatars tracks with FLAME 2023 "
                                                r"\(flame2023.pkl\)"):
        load_gaussian_avatars_flame(tmp_path / "old.npz")
    old_pickle = tmp_path / "generic_model.pkl"  # FLAME 2020's file name
    old_pickle.write_bytes(pkl.read_bytes())
    with pytest.raises(ImportFormatError, match=r"the file name says FLAME is '2020': GaussianAvatars tracks with "
                                                r"FLAME 2023"):
        load_gaussian_avatars_flame(old_pickle)


@pytest.mark.parametrize("n_expr", [50, 200])
def test_loader_refuses_other_expression_counts(model, tmp_path, n_expr):
    other = dict(model, shapedirs=np.concatenate([model["shapedirs"][:, :, :300],
                                                  np.zeros((5023, 3, n_expr))], 2))
    npz = ga.write_flame_npz(tmp_path / "flame.npz", other)
    with pytest.raises(ImportFormatError, match=rf"'shapedirs' has {300 + n_expr} columns: 300 shape \+ {n_expr} "
                                                r"expression; GaussianAvatars needs 300 \+ 100"):
        load_gaussian_avatars_flame(npz)
    pkl = ga.write_flame_pickle_model(tmp_path / "flame.pkl", other)
    with pytest.raises(ImportFormatError, match=rf"'shapedirs' has shape \[5023, 3, {300 + n_expr}\]"):
        load_gaussian_avatars_flame(pkl)


def test_loader_refuses_other_meshes(tmp_path):
    short = flame_model(FlameSpec(n_vertices=5000, n_faces=9976))
    with pytest.raises(CheckpointError, match=r"'v_template' has 5000 vertices; GaussianAvatars' teeth are built on "
                                              r"FLAME's 5023"):
        load_gaussian_avatars_flame(ga.write_flame_npz(tmp_path / "short.npz", short))
    few_faces = flame_model(FlameSpec(n_vertices=5023, n_faces=9000))
    with pytest.raises(CheckpointError, match=r"'faces' has 9000 triangles"):
        load_gaussian_avatars_flame(ga.write_flame_npz(tmp_path / "faces.npz", few_faces))
    arrays = load_flame_npz(ga.write_flame_npz(tmp_path / "faces.npz", few_faces), 300, 100)
    with pytest.raises(CheckpointError, match="'faces'"):
        add_gaussian_avatars_teeth(arrays)


def test_loader_refuses_unreadable_files(tmp_path):
    with pytest.raises(ImportFormatError, match="cannot read"):
        load_gaussian_avatars_flame(tmp_path / "missing.pkl")
    text = tmp_path / "notes.pkl"
    text.write_text("not a model")
    with pytest.raises(ImportFormatError):
        load_gaussian_avatars_flame(text)
    no_dirs = tmp_path / "empty.npz"
    np.savez(no_dirs, v_template=np.zeros((3, 3)))
    with pytest.raises(ImportFormatError, match="no 'shapedirs'"):
        load_gaussian_avatars_flame(no_dirs)


# ------------------------------------------------------------------------------------ the test-side helpers


def test_written_avatar_reads_back(avatar, tmp_path, model):
    assert avatar["ply_path"].parent.name == "iteration_30000"
    assert avatar["param_path"] == avatar["ply_path"].parent / "flame_param.npz"
    data = PlyData.read(str(avatar["ply_path"]))
    assert data.byte_order == "<" and not data.text
    vertex = data["vertex"]
    names = [p.name for p in vertex.properties]
    assert names == ga.ply_field_names(3) and len(names) == 6 + 3 + 45 + 1 + 3 + 4 + 1
    for name in names:
        assert vertex[name].dtype == np.float32, name
        np.testing.assert_array_equal(vertex[name], avatar["ply"][name])
    binding = vertex["binding_0"].astype(np.int64)
    assert binding.min() >= 0 and binding.max() < ga.GA_FACES and (binding >= ga.FLAME_FACES).sum() > 100
    norms = np.linalg.norm(np.stack([vertex[f"rot_{i}"] for i in range(4)], 1), axis=1)
    assert norms.min() < 0.8 and norms.max() > 1.5  # stored unnormalised, as training leaves them
    with np.load(avatar["param_path"]) as params:
        shapes = {key: params[key].shape for key in params.files}
        assert all(params[key].dtype == np.float32 for key in params.files)
    assert shapes == {"shape": (300,), "expr": (8, 100), "rotation": (8, 3), "neck_pose": (8, 3), "jaw_pose": (8, 3),
                      "eyes_pose": (8, 6), "translation": (8, 3), "static_offset": (1, 5143, 3),
                      "dynamic_offset": (8, 5143, 3)}
    jaw = avatar["params"]["jaw_pose"][:, 0]
    assert jaw[0] == 0 and jaw[-1] > 0.2 and (np.diff(jaw) > 0).all()
    small = ga.write_gaussian_avatar(tmp_path, model, n_gaussians=10, frames=2, sh_degree=0, iteration=7,
                                     drop_fields=("opacity", "dynamic_offset"),
                                     edit_params=lambda p: p.update(shape=p["shape"][:100]))
    written = PlyData.read(str(tmp_path / "point_cloud" / "iteration_7" / "point_cloud.ply"))
    names = [p.name for p in written["vertex"].properties]
    assert "opacity" not in names and not any(n.startswith("f_rest") for n in names) and len(names) == 17
    with np.load(small["param_path"]) as params:
        assert "dynamic_offset" not in params.files and params["shape"].shape == (100,)


def test_reference_forward_at_zero_pose(model, avatar):
    reference = ga.ga_flame_with_teeth(model)
    params = {key: np.array(value) for key, value in avatar["params"].items()}
    for key in ("rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation"):
        params[key][:] = 0
    dirs = reference["shapedirs"]
    want = (reference["v_template"] + dirs[:, :, :300] @ params["shape"].astype(np.float64)
            + dirs[:, :, 300:] @ params["expr"][3].astype(np.float64) + params["static_offset"][0])
    np.testing.assert_allclose(ga.ga_flame_vertices(reference, params, 3), want, rtol=0, atol=1e-12)


def test_reference_forward_rotations(model, avatar):
    reference = ga.ga_flame_with_teeth(model)
    params = {key: np.array(value) for key, value in avatar["params"].items()}
    for key in ("rotation", "neck_pose", "jaw_pose", "eyes_pose"):
        params[key][:] = 0
    rest = ga.ga_flame_vertices(reference, params, 0) - params["translation"][0]
    joints = reference["J_regressor"] @ rest  # at zero pose the vertices are the shaped ones
    params["rotation"][0] = [0.0, 0.5, 0.0]  # the whole head turns about the root joint
    turn = np.array([[np.cos(0.5), 0, np.sin(0.5)], [0, 1, 0], [-np.sin(0.5), 0, np.cos(0.5)]])
    want = (rest - joints[0]) @ turn.T + joints[0] + params["translation"][0]
    np.testing.assert_allclose(ga.ga_flame_vertices(reference, params, 0), want, rtol=0, atol=1e-12)
    params["rotation"][0] = 0
    params["jaw_pose"][0] = [0.3, 0.0, 0.0]  # the jaw opens: lower teeth turn about the jaw joint, upper stay
    opened = ga.ga_flame_vertices(reference, params, 0) - params["translation"][0]
    upper, lower = _rows(UPPER_ROWS), _rows(LOWER_ROWS)
    np.testing.assert_allclose(opened[upper], rest[upper], rtol=0, atol=1e-12)
    turn = ga.rodrigues(params["jaw_pose"][0])  # float32 0.3, as stored
    np.testing.assert_allclose(opened[lower], (rest[lower] - joints[2]) @ turn.T + joints[2], rtol=0, atol=1e-12)
    assert (opened[lower, 1] < rest[lower, 1] - 0.003).all()  # the front of the jaw drops


def test_reference_binding_on_one_triangle():
    vertices = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.5, 1.0, 0.0]])
    ply = {"x": [1.0], "y": [0.0], "z": [0.5], "scale_0": [0.0], "scale_1": [np.log(2.0)], "scale_2": [0.0],
           "rot_0": [2.0], "rot_1": [0.0], "rot_2": [0.0], "rot_3": [0.0], "binding_0": [0.0]}
    xyz, scale, quat = ga.ga_world_gaussians(vertices, np.array([[0, 1, 2]]), ply)
    # a0 = +x, a1 = n(a0 x (v2 - v0)) = +z, a2 = -(a1 x a0) = -y; k = (2 + 1) / 2; centre (2.5, 1, 0) / 3
    np.testing.assert_allclose(xyz[0], [2.5 / 3 + 1.5, 1 / 3 - 0.75, 0.0], atol=1e-12)
    np.testing.assert_allclose(scale[0], [1.5, 3.0, 1.5], atol=1e-12)
    np.testing.assert_allclose(quat[0], [np.sqrt(0.5), np.sqrt(0.5), 0.0, 0.0], atol=1e-12)  # +90 degrees about x


def test_reference_binding_composes_rotations(model, avatar):
    """quat(R_face) (x) q rotates like R_face @ R(q); positions sit within a few triangle sizes of their face."""
    reference = ga.ga_flame_with_teeth(model)
    vertices = ga.ga_flame_vertices(reference, avatar["params"], 5)
    xyz, scale, quat = ga.ga_world_gaussians(vertices, reference["f"], avatar["ply"])
    rot, k, centre = ga.ga_triangle_frames(vertices, reference["f"])
    binding = avatar["ply"]["binding_0"].astype(np.int64)
    q = np.stack([avatar["ply"][f"rot_{i}"] for i in range(4)], 1).astype(np.float64)
    want = rot[binding] @ _quat_matrix(q)
    np.testing.assert_allclose(_quat_matrix(quat), want, atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-9)
    distance = np.linalg.norm(xyz - centre[binding], axis=1) / k[binding]
    assert distance.max() < 3.0 and np.median(distance) > 0.2
    np.testing.assert_allclose(scale / k[binding, None], np.exp(np.stack([avatar["ply"][f"scale_{i}"] for i in
                                                                           range(3)], 1)), rtol=1e-6)


def _quat_matrix(q: np.ndarray) -> np.ndarray:
    """(w, x, y, z) [N, 4] (any norm) -> [N, 3, 3]."""
    w, x, y, z = np.moveaxis(q / np.linalg.norm(q, axis=1, keepdims=True), 1, 0)
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)
