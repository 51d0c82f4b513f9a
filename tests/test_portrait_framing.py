"""Portrait framing, the default camera of `gt-import lam` and `gt-import gaussian-avatars` (docs/import.md,
"Portrait framing"): the head's box (the Gaussians or vertices the skin moves with the head) at PORTRAIT_FILL of the
frame's height, centred; `--camera source` keeps the source's framing. The boxes are computed here from the
fixtures' own skinning, not by the importer's helpers."""

from __future__ import annotations

import numpy as np
import pytest
from gaussian_avatars import synthetic_flame, write_flame_npz, write_gaussian_avatar
from lam_avatars import HEAD_CENTRE, AvatarSpec, expected_centres, write_avatar_zip
from typer.testing import CliRunner

from gaussiantalker.cli.imports import app
from gaussiantalker.exporter.export.bundle_export import export_bundle
from gaussiantalker.exporter.export.checkpoint import load_checkpoint
from gaussiantalker.exporter.imports.portrait import PORTRAIT_FILL, box_height_fill, head_box, portrait_camera
from gaussiantalker.exporter.imports.sources.gaussian_avatars import (
    GaussianAvatarsOptions,
    avatar_camera,
    first_frame_vertices,
    import_gaussian_avatars,
)
from gaussiantalker.exporter.imports.sources.lam import LamOptions, import_lam, lam_camera
from gaussiantalker.runtime import TalkingHead
from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.errors import ImportFormatError

NECK_BELOW = -0.04  # the LAM fixture's vertices this far below the head's centre are skinned to the neck


def _centre_offset(camera: Camera, low: np.ndarray, high: np.ndarray) -> float:
    """Pixels between the box centre's projection and the frame's centre."""
    view = camera.R @ ((low + high) / 2.0) + camera.t
    return float(np.hypot(camera.fx * view[0] / view[2] + camera.cx - camera.width / 2.0,
                          camera.fy * view[1] / view[2] + camera.cy - camera.height / 2.0))


def _same_camera(a: Camera, b: Camera) -> bool:
    return bool(np.allclose(a.R, b.R, atol=1e-9) and np.allclose(a.t, b.t, atol=1e-9)
                and (a.fx, a.fy, a.cx, a.cy, a.width, a.height) == pytest.approx((b.fx, b.fy, b.cx, b.cy, b.width,
                                                                                  b.height)))


@pytest.mark.parametrize("size", [(512, 512), (640, 360), (64, 64)])
@pytest.mark.parametrize("seed", range(3))
def test_portrait_camera_frames_the_box_at_the_fill_centred(seed, size):
    rng = np.random.default_rng(seed)
    low = rng.uniform(-1, 1, 3)
    high = low + rng.uniform([0.1, 0.2, 0.1], [0.2, 0.3, 0.3])
    camera = portrait_camera(low, high, *size)
    assert box_height_fill(camera, low, high) == pytest.approx(PORTRAIT_FILL, abs=1e-9)
    assert _centre_offset(camera, low, high) < 1e-6
    assert np.allclose(camera.R.T @ [0, 0, 1], [0, 0, -1])  # level, looking at the face (toward +z) from its front


def test_a_box_wider_than_a_tall_frame_is_framed_by_its_width():
    low, high = np.array([-0.3, -0.1, -0.1]), np.array([0.3, 0.1, 0.1])
    camera = portrait_camera(low, high, 200, 600)
    assert box_height_fill(camera, low, high) < PORTRAIT_FILL
    corners = np.array([[x, y, z] for x in (low[0], high[0]) for y in (low[1], high[1]) for z in (low[2], high[2])])
    view = corners @ camera.R.T + camera.t
    columns = camera.fx * view[:, 0] / view[:, 2] + camera.cx
    assert (columns.max() - columns.min()) / camera.width == pytest.approx(0.9, abs=1e-9)


def test_head_box_leaves_out_a_few_stray_points():
    points = np.random.default_rng(0).uniform(-0.1, 0.1, (1000, 3))
    points[:5] = 50.0
    low, high = head_box(points)
    assert (high < 0.11).all() and (low > -0.11).all()
    with pytest.raises(ValueError, match="finite"):
        head_box(np.array([[0.0, np.nan, 0.0]]))


@pytest.fixture(scope="module")
def lam_zip(tmp_path_factory):
    return write_avatar_zip(tmp_path_factory.mktemp("lam") / "avatar.zip", AvatarSpec(neck_below=NECK_BELOW))


def test_lam_default_camera_is_a_portrait_of_the_head_bone_gaussians(lam_zip):
    speaker = import_lam(lam_zip, progress=False)
    spec = AvatarSpec(neck_below=NECK_BELOW)
    from lam_avatars import rest_vertices

    on_head = rest_vertices(spec)[:, 1] - HEAD_CENTRE[1] >= NECK_BELOW
    centres = expected_centres(spec, {})
    low, high = np.percentile(centres[on_head], 1, axis=0), np.percentile(centres[on_head], 99, axis=0)
    assert 0 < on_head.sum() < len(on_head)  # the fixture really puts some Gaussians on the neck
    assert np.allclose(speaker.source["head_box"], [low, high], atol=1e-6)
    assert low[1] > centres[:, 1].min() + 0.01  # the neck's Gaussians are out of the box
    assert speaker.source["camera"] == "portrait"
    assert box_height_fill(speaker.camera, low, high) == pytest.approx(PORTRAIT_FILL, abs=1e-6)
    assert _centre_offset(speaker.camera, low, high) < 1e-3
    # The source's camera: LAM's renderer's, placed on all the Gaussians' box as before.
    source = import_lam(lam_zip, LamOptions(camera="source"), progress=False)
    all_low, all_high = np.percentile(centres, 1, axis=0), np.percentile(centres, 99, axis=0)
    assert _same_camera(source.camera, lam_camera((all_low + all_high) / 2.0, float(all_high[1] - all_low[1])))
    with pytest.raises(ValueError, match="camera must be one of portrait, source"):
        import_lam(lam_zip, LamOptions(camera="front"), progress=False)


def test_skin_weights_naming_a_missing_joint_are_refused(tmp_path):
    path = write_avatar_zip(tmp_path / "bad.zip", AvatarSpec(skip=("joint index",)))
    with pytest.raises(ImportFormatError, match="JOINTS_0 names joints 0 to 7; the skin has 3"):
        import_lam(path, progress=False)


def test_the_runtime_draws_the_head_at_the_portrait_size(lam_zip, tmp_path):
    """The bundle carries the camera: the drawn head's top lies at the box's top row (less the Gaussians' own extent,
    under 0.06 of the frame here), the neck's Gaussians below the box's bottom row."""
    speaker = import_lam(lam_zip, progress=False)
    bundle = export_bundle(speaker, tmp_path / "lam.gtb", progress=False).path
    head = TalkingHead(bundle, resolution=(128, 128))
    alpha = np.asarray(head.frame_renderer.frame(head.driver.drive(), "rgba_float"))[..., 3]
    rows = np.nonzero((alpha > 0.5).any(axis=1))[0] / 128
    box_top, box_bottom = 0.5 - PORTRAIT_FILL / 2, 0.5 + PORTRAIT_FILL / 2
    assert box_top - 0.06 < rows.min() < box_top + 0.01
    assert rows.max() > box_bottom


def test_cli_camera_option(lam_zip, tmp_path):
    runner = CliRunner()
    result = runner.invoke(app, ["lam", str(lam_zip), "-o", str(tmp_path / "a.ckpt"), "--camera", "source",
                                 "--no-voice", "-q"])
    assert result.exit_code == 0, result.output
    assert load_checkpoint(tmp_path / "a.ckpt").source["camera"] == "source"
    result = runner.invoke(app, ["lam", str(lam_zip), "-o", str(tmp_path / "b.ckpt"), "--camera", "front"])
    assert result.exit_code == 2 and "--camera must be one of portrait, source" in result.output
    assert not (tmp_path / "b.ckpt").exists()


@pytest.fixture(scope="module")
def ga_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ga")
    model = synthetic_flame(0)
    write_flame_npz(folder / "flame.npz", model)
    write_gaussian_avatar(folder / "avatar", model, n_gaussians=200, frames=2)
    return folder, model


def test_gaussian_avatars_default_camera_is_a_portrait_of_the_head(ga_folder):
    folder, model = ga_folder
    speaker = import_gaussian_avatars(folder / "avatar", folder / "flame.npz", GaussianAvatarsOptions(resolution=96))
    vertices = first_frame_vertices(speaker)
    weights = speaker.flame_arrays.lbs_weights
    on_head = weights[:, 1:].sum(axis=1) > weights[:, 0]  # FLAME's neck joint and below outweigh the root
    assert 0 < on_head.sum() < len(on_head)
    low, high = np.percentile(vertices[on_head], 1, axis=0), np.percentile(vertices[on_head], 99, axis=0)
    assert np.allclose(speaker.source["head_box"], [low, high], atol=1e-6)
    assert speaker.source["camera"] == "portrait"
    assert box_height_fill(speaker.camera, low, high) == pytest.approx(PORTRAIT_FILL, abs=1e-6)
    assert _centre_offset(speaker.camera, low, high) < 1e-3
    source = import_gaussian_avatars(folder / "avatar", folder / "flame.npz",
                                     GaussianAvatarsOptions(resolution=96, camera="source"))
    assert _same_camera(source.camera, avatar_camera(source, 96))
    assert box_height_fill(source.camera, low, high) > box_height_fill(speaker.camera, low, high)


def test_framing_bench_reports_both_cameras(lam_zip, tmp_path):
    from tools.bench.framing import framing_table, run_framing

    result = run_framing([lam_zip], None, tmp_path, rounds=1)
    rows = result["avatar.zip"]
    assert rows["portrait"]["frame_ms"] > 0 and rows["source"]["frame_ms"] > 0
    assert rows["portrait"]["head_box_height"] == pytest.approx(PORTRAIT_FILL, abs=1e-6)
    assert rows["source"]["head_box_height"] != pytest.approx(PORTRAIT_FILL, abs=0.01)
    assert 0 < rows["source"]["covered"] < rows["portrait"]["covered"] < 1
    table = framing_table(result)
    assert table.count("| avatar.zip |") == 2 and "portrait / source" in table
    assert (tmp_path / "avatar.zip.png").is_file()
