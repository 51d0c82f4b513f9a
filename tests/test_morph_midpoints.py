"""Midpoint vertices (exporter/export/morph_midpoints.py, docs/deformation.md "Midpoint vertices"): a subdivided
mesh's edge vertices found from the rig's triangles and numbers, derived in the ARKit deformation graph from their
ends, and the graph's Gaussians equal to the torch speaker's, whole and pruned; what is not exactly a midpoint stays
stored; the triangles travel from LAM's skin.glb through the checkpoint."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from lam_avatars import AvatarSpec, mesh_faces, rest_vertices, write_avatar_zip

from gaussiantalker.exporter.export.arkit_graph import ArkitDeformationGraph
from gaussiantalker.exporter.export.bundle_export import export_bundle
from gaussiantalker.exporter.export.checkpoint import load_checkpoint, save_checkpoint
from gaussiantalker.exporter.export.morph_midpoints import MIDPOINT_TOLERANCE_M, find_midpoints, morph_rows
from gaussiantalker.exporter.export.presets import ExportSettings, get_preset
from gaussiantalker.exporter.imports.sources.lam import import_lam
from gaussiantalker.runtime.stages import open_backend
from gaussiantalker.sdk.bundle import Bundle
from gaussiantalker.sdk.errors import CheckpointError, ImportFormatError

SPEC = AvatarSpec(rings=7, segments=10, subdivided=True)
COARSE = SPEC.rings * SPEC.segments
# The graph's Gaussian centres against ArkitSpeaker.deform: float32 sums of a different order (the derived offsets
# are means of their ends' sums), well under the tolerance a derived vertex may sit from the rig.
CENTRE_ATOL_M = 2e-6


@pytest.fixture(scope="module")
def avatar(tmp_path_factory):
    return import_lam(write_avatar_zip(tmp_path_factory.mktemp("sub") / "avatar.zip", SPEC), progress=False)


def _rig_arrays(speaker):
    rig = speaker.rig
    return rig.rest.numpy(), rig.morphs.numpy(), rig.faces.numpy()


def _drives(count: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    weights = (rng.uniform(0, 1, (count, 52)) * (rng.random((count, 52)) < 0.4)).astype(np.float32)
    return (torch.from_numpy(weights), torch.from_numpy(rng.normal(0, 0.2, (count, 3)).astype(np.float32)),
            torch.from_numpy(rng.normal(0, 0.01, (count, 3)).astype(np.float32)), torch.zeros(count, 3))


def test_a_subdivided_mesh_has_every_edge_vertex_found(avatar):
    rest, morphs, faces = _rig_arrays(avatar)
    assert rest.shape[0] > COARSE and np.array_equal(faces, mesh_faces(SPEC))
    found = find_midpoints(rest, morphs, faces)
    assert np.array_equal(found[:, 0], np.arange(COARSE, rest.shape[0]))  # every edge vertex, no grid vertex
    grid = rest_vertices(AvatarSpec(rings=SPEC.rings, segments=SPEC.segments))
    np.testing.assert_allclose((grid[found[:, 1]] + grid[found[:, 2]]) / 2, rest[found[:, 0]], atol=1e-6)


def test_a_vertex_off_its_midpoint_stays_stored(avatar):
    rest, morphs, faces = _rig_arrays(avatar)
    moved = morphs.copy()
    jaw = int(np.flatnonzero(np.abs(morphs).reshape(52, -1).max(1) > 0)[0])
    victim = COARSE + int(np.flatnonzero(np.abs(morphs[jaw, COARSE:]).max(1) > 0)[0])
    moved[jaw, victim, 1] += 2 * MIDPOINT_TOLERANCE_M
    found = find_midpoints(rest, moved, faces)
    assert victim not in found[:, 0] and len(found) == rest.shape[0] - COARSE - 1
    moved[jaw, victim, 1] = morphs[jaw, victim, 1] + 0.5 * MIDPOINT_TOLERANCE_M  # within the tolerance: derived
    assert victim in find_midpoints(rest, moved, faces)[:, 0]


def test_the_same_rig_asked_again_is_not_searched_again(avatar, monkeypatch):
    """An export that derives midpoints and orders its Gaussians spatially asks for the same rig's table twice: the
    second answer is the first one's copy (a caller that changes it changes nothing kept), and a changed rig, or
    another tolerance, is searched again."""
    import gaussiantalker.exporter.export.morph_midpoints as module

    rest, morphs, faces = _rig_arrays(avatar)
    searched = []
    found_by_search = module._found
    monkeypatch.setattr(module, "_found", lambda *args: searched.append(1) or found_by_search(*args))
    monkeypatch.setattr(module, "_FOUND", {})
    first = find_midpoints(rest, morphs, faces)
    first[:] = -1
    again = find_midpoints(rest, morphs, faces)
    assert len(searched) == 1 and np.array_equal(again[:, 0], np.arange(COARSE, rest.shape[0]))
    moved = morphs.copy()
    moved[0, COARSE, 0] += 1.0
    assert COARSE not in find_midpoints(rest, moved, faces)[:, 0] and len(searched) == 2
    find_midpoints(rest, morphs, faces, tolerance=MIDPOINT_TOLERANCE_M / 2)
    assert len(searched) == 3 and len(module._FOUND) == 3


def test_no_derived_vertex_is_another_ones_end():
    """0-1-2 on a line with 1 their midpoint, and 3 the midpoint of 0 and 1: only one of 1 and 3 can be derived
    (1, whose ends are stored vertices), so nothing waits on a derived vertex."""
    rest = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0.5, 0, 0], [1, 1, 0], [1, -2, 0]], np.float64)
    morphs = rest[None] * 0.01
    faces = np.array([[0, 3, 4], [3, 1, 4], [1, 2, 4], [0, 1, 5]])  # 1's neighbours: 0, 2, 3, 4, 5
    assert find_midpoints(rest, morphs, faces).tolist() == [[1, 0, 2]]


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(4, 40), st.floats(0.0, 1.0))
def test_midpoints_of_any_mesh_are_exact_and_one_level(seed, n_vertices, share):
    """Random meshes with random vertices made midpoints of two others: whatever is found is a midpoint within the
    tolerance, its ends are not derived, and morph_rows puts every Gaussian on its vertex's row."""
    rng = np.random.default_rng(seed)
    rest = rng.normal(size=(n_vertices, 3))
    morphs = rng.normal(size=(3, n_vertices, 3)) * 0.01
    faces = rng.integers(0, n_vertices, (2 * n_vertices, 3))
    for v in np.flatnonzero(rng.random(n_vertices) < share):
        a, b = rng.choice(n_vertices, 2, replace=False)
        rest[v], morphs[:, v] = (rest[a] + rest[b]) / 2, (morphs[:, a] + morphs[:, b]) / 2
        faces = np.concatenate([faces, [[v, a, b]]])
    found = find_midpoints(rest, morphs, faces)
    v, a, b = found.T
    assert np.abs(morphs[:, a] + morphs[:, b] - 2 * morphs[:, v]).max(initial=0) <= 2 * MIDPOINT_TOLERANCE_M
    assert not set(v.tolist()) & (set(a.tolist()) | set(b.tolist()))
    vertex = rng.integers(0, n_vertices, rng.integers(1, 2 * n_vertices))
    rows = morph_rows(vertex, found)
    table = np.concatenate([morphs[:, rows.sources],
                            (morphs[:, rows.sources[rows.ends[0]]] + morphs[:, rows.sources[rows.ends[1]]]) / 2], 1)
    np.testing.assert_allclose(table[:, rows.gaussian_rows], morphs[:, vertex], atol=2 * MIDPOINT_TOLERANCE_M)


@pytest.mark.parametrize("budget", [None, 0.6, 0.3, "shuffled"])
def test_the_graph_derives_edge_vertices_and_equals_the_speaker(avatar, budget):
    """Whole and pruned (its Gaussians on a subset of vertices: some ends are then kept for their midpoints only;
    the graph slices its rows), and in another order (the graph gathers them): the graph stores the grid's morph
    targets only and its centres equal ArkitSpeaker.deform's."""
    speaker, rng = avatar, np.random.default_rng(3)
    if budget == "shuffled":
        speaker = speaker.subset(torch.from_numpy(rng.permutation(speaker.gaussians.count)))
    elif budget is not None:
        keep = np.sort(rng.choice(speaker.gaussians.count, int(budget * speaker.gaussians.count), replace=False))
        speaker = speaker.subset(torch.from_numpy(keep))
    graph = ArkitDeformationGraph(speaker, midpoints=True)
    assert graph.midpoint_ends is not None and graph.n_sources <= COARSE
    assert (graph.gaussian_rows is not None) == (budget == "shuffled")
    assert graph.morph_basis.shape[1] == 3 * graph.n_sources
    drives = _drives(4)
    with torch.no_grad():
        want, got = speaker.deform(*drives), graph(*drives)
    np.testing.assert_allclose(got[0].numpy(), want[0].numpy(), atol=CENTRE_ATOL_M)
    for ours, theirs in zip(got[1:], want[1:], strict=True):
        np.testing.assert_allclose(ours.numpy(), theirs.numpy(), atol=1e-6)
    stored = ArkitDeformationGraph(speaker)  # the knob off: every vertex stored, nothing derived
    assert stored.midpoint_ends is None and stored.n_sources == len(np.unique(speaker.gaussians.vertex.numpy()))


def test_bundles_of_the_reduced_presets_derive_them(avatar, tmp_path):
    """`midpoints` is on in every reduced preset and off in quality (exact parity); the bundle's graph, run by the
    runtime, gives the centres the torch graph gives; its morph basis holds the grid's vertices only."""
    assert not get_preset("quality").export.midpoints and not ExportSettings().midpoints
    assert all(get_preset(name).export.midpoints for name in ("balanced", "compact", "fast", "mobile"))
    assert not ExportSettings(midpoints=True).lossless
    settings = ExportSettings(midpoints=True)
    bundle = Bundle(export_bundle(avatar, tmp_path / "mid.gtb", settings=settings, progress=False).path)
    assert bundle.buffer("deform/morph_basis").shape[1] == 3 * COARSE
    assert bundle.buffer("deform/midpoint_ends").shape == (2, rest_vertices(SPEC).shape[0] - COARSE)
    backend = open_backend(bundle, "onnxruntime", threads=1)
    weights, rotation, translation, centre = (t.numpy() for t in _drives(3, seed=5))
    out = backend.run("deform", {"blendshapes": weights, "head_rotation": rotation,
                                 "head_translation": translation, "camera_center": centre})
    with torch.no_grad():
        want = avatar.deform(*_drives(3, seed=5))[0].numpy()
    np.testing.assert_allclose(out["means"], want, atol=CENTRE_ATOL_M)
    plain = Bundle(export_bundle(avatar, tmp_path / "plain.gtb", progress=False).path)
    assert not plain.has_buffer("deform/midpoint_ends")
    assert plain.buffer("deform/morph_basis").size > bundle.buffer("deform/morph_basis").size


def test_the_triangles_travel_through_the_checkpoint(avatar, tmp_path):
    loaded = load_checkpoint(save_checkpoint(avatar, tmp_path / "sub.ckpt"))
    assert torch.equal(loaded.rig.faces, avatar.rig.faces)
    payload = torch.load(tmp_path / "sub.ckpt", weights_only=True)
    del payload["blendshape_rig"]["faces"]  # a checkpoint from before the triangles were kept
    torch.save(payload, tmp_path / "old.ckpt")
    old = load_checkpoint(tmp_path / "old.ckpt")
    assert old.rig.faces is None and ArkitDeformationGraph(old, midpoints=True).midpoint_ends is None
    for bad, words in ((torch.tensor([[0, 1, 10**6]]), "outside"), (torch.zeros(2, 3), "dtype"),
                       (torch.zeros(3, dtype=torch.int64), "shape")):
        payload["blendshape_rig"]["faces"] = bad
        torch.save(payload, tmp_path / "bad.ckpt")
        with pytest.raises(CheckpointError, match=words):
            load_checkpoint(tmp_path / "bad.ckpt")


def test_a_glb_whose_indices_are_not_triangles_of_its_vertices_is_refused(tmp_path, monkeypatch):
    import lam_avatars

    real = lam_avatars.mesh_faces
    monkeypatch.setattr(lam_avatars, "mesh_faces", lambda spec: real(spec) + 10**6)
    with pytest.raises(ImportFormatError, match="indices"):
        import_lam(write_avatar_zip(tmp_path / "bad.zip", SPEC), progress=False)
