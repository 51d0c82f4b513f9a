"""Spatial order of the Gaussians (exporter/export/spatial_order.py, docs/precision.md "Spatial order"): a Morton
walk of their positions, ARKit Gaussians on derived vertices after the stored ones so the graph still slices; the
bundle draws the same frames in either order; `compact` takes it (with codebooks and deflated buffers) for an ARKit
avatar, and its knobs reach `gt-export`."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from lam_avatars import AvatarSpec, write_avatar_zip
from typer.testing import CliRunner

from gaussiantalker.exporter.export.arkit_graph import ArkitDeformationGraph
from gaussiantalker.exporter.export.bundle_export import export_bundle, resolve_settings
from gaussiantalker.exporter.export.checkpoint import save_checkpoint
from gaussiantalker.exporter.export.presets import ExportSettings, get_preset
from gaussiantalker.exporter.export.spatial_order import morton_order, neutral_positions, spatial_order
from gaussiantalker.exporter.imports.sources.lam import import_lam
from gaussiantalker.runtime import TalkingHead
from gaussiantalker.sdk.bundle import Bundle
from gaussiantalker.sdk.drive import BlendshapeDrive, HeadPose
from gaussiantalker.sdk.errors import BundleError
from gaussiantalker.sdk.image import psnr_db

SPEC = AvatarSpec(rings=7, segments=10, subdivided=True)
SIZE = 96
# Frames of the same Gaussians in two orders: equal but where two of them lie at the same depth, whose blend order
# the sort's tie-break decides; the grid avatar's splats are large and overlap, so a few pixels move by a level.
SAME_FRAMES_PSNR_DB = 50.0


@pytest.fixture(scope="module")
def avatar(tmp_path_factory):
    return import_lam(write_avatar_zip(tmp_path_factory.mktemp("order") / "avatar.zip", SPEC), progress=False)


@pytest.fixture(scope="module")
def larger_avatar(tmp_path_factory):
    """~2,400 Gaussians: enough that compact's per-Gaussian buffers are past fp16's size limit (QUANT_MIN_VALUES)."""
    spec = AvatarSpec(rings=20, segments=30, subdivided=True)
    return import_lam(write_avatar_zip(tmp_path_factory.mktemp("larger") / "avatar.zip", spec), progress=False)


def test_morton_order_walks_a_grid_cell_by_cell():
    """On the 2x2x2 corners of a cube the Morton code is x + 2y + 4z; points far apart in the input but in one
    cell of the walk come out next to each other."""
    corners = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], float)
    shuffled = np.random.default_rng(0).permutation(8)
    order = morton_order(corners[shuffled], bits=1)
    np.testing.assert_array_equal(corners[shuffled][order], corners)
    line = np.stack([np.linspace(0, 1, 50), np.zeros(50), np.zeros(50)], 1)[::-1]
    np.testing.assert_array_equal(morton_order(line), np.arange(50)[::-1])


@pytest.mark.parametrize("midpoints", [False, True])
def test_the_order_is_a_permutation_derived_gaussians_last_and_the_graph_still_slices(avatar, midpoints):
    order = spatial_order(avatar, midpoints=midpoints)
    assert sorted(order.tolist()) == list(range(avatar.gaussians.count))
    ordered = avatar.subset(torch.from_numpy(order))
    graph = ArkitDeformationGraph(ordered, midpoints=midpoints)
    assert graph.gaussian_rows is None  # a slice, not a gather
    if midpoints:
        ends = graph.midpoint_ends.numpy()
        assert np.all(ends[0] < ends[1])  # each pair nearest row first
        derived = len(ends[0])
        assert 0 < derived < avatar.gaussians.count
    else:
        positions = neutral_positions(ordered)
        np.testing.assert_array_equal(morton_order(positions), np.arange(len(positions)))


def _frames(path, count: int = 4) -> np.ndarray:
    rng = np.random.default_rng(4)
    with TalkingHead(path, resolution=(SIZE, SIZE), composite=False) as head:
        names = head.driver.param_names
        drives = [BlendshapeDrive.make({name: float(rng.uniform(0, 1)) for name in names[:8]},
                                       HeadPose.make([0.1 * k, -0.1 * k, 0.0]), names) for k in range(count)]
        return np.stack([head.render(drive) for drive in drives])


def test_a_bundle_in_spatial_order_draws_the_same_frames(avatar, tmp_path):
    plain = export_bundle(avatar, tmp_path / "plain.gtb", settings=ExportSettings(midpoints=True), progress=False)
    ordered = export_bundle(avatar, tmp_path / "ordered.gtb", settings=ExportSettings(midpoints=True,
                                                                                         spatial_order=True),
                            progress=False)
    assert ExportSettings(spatial_order=True, deflate=True).lossless
    a, b = _frames(plain.path), _frames(ordered.path)
    assert psnr_db(a, b) >= SAME_FRAMES_PSNR_DB
    opacity = [Bundle(result.path).buffer("deform/opacity") for result in (plain, ordered)]
    assert not np.array_equal(*opacity) and np.array_equal(np.sort(opacity[0]), np.sort(opacity[1]))


def test_verify_compares_a_spatially_ordered_graph_gaussian_by_gaussian(avatar, tmp_path):
    """`gt-export --verify` puts the torch speaker's Gaussians in the bundle's order before comparing the graphs, so
    an fp32 bundle in spatial order is held to fp32 parity (graphs within 1e-4, frames >= 50 dB)."""
    from gaussiantalker.exporter.verify.bundle_verify import verify_bundle

    result = export_bundle(avatar, tmp_path / "ordered.gtb", settings=ExportSettings(spatial_order=True),
                           progress=False)
    assert result.label == "fp32"
    outcome = verify_bundle(avatar, result.path, frames=4, resolution=(96, 96), progress=False)
    deform = outcome["graphs"]["deform"]
    assert "note" not in deform and deform["cases"] > 0 and deform["tolerance_rel"] is not None
    assert deform["passed"] and outcome["passed"]


def test_compact_has_its_own_settings_for_an_arkit_avatar(larger_avatar, tmp_path):
    """`compact` for an ARKit rig: codebooks, 8-bit rest points, spatial order, deflated buffers; the bundle says
    `compact`, its codebooks hold at most the asked entries, and it plays."""
    compact = get_preset("compact")
    arkit = compact.export_for("arkit")
    assert compact.export_for("flame") == compact.export and arkit != compact.export
    assert arkit.spatial_order and arkit.deflate and dict(arkit.buffer_codecs)["deform/rotation"] == "vq/256"
    assert resolve_settings(preset="compact", rig="arkit")[2] == "compact"
    result = export_bundle(larger_avatar, tmp_path / "compact.gtb", preset="compact", progress=False)
    assert result.label == "compact"
    bundle = Bundle(result.path)
    entries = bundle.manifest["buffers"]
    assert entries["deform/rotation"]["codec"] == {"name": "vq", "entries": 256}
    assert entries["deform/log_scale"]["codec"] == {"name": "vq", "entries": 1024}
    assert entries["deform/rest_points"]["codec"] == {"name": "q8", "chunk": 64}
    assert any(entry.get("compression") == "zlib" for entry in entries.values())
    assert bundle.manifest["export_settings"]["spatial_order"] is True
    frames = _frames(result.path, 2)
    assert np.isfinite(frames).all() and frames.std() > 0


def test_buffer_codecs_override_the_group_and_are_checked():
    settings = ExportSettings(gaussians="q8", buffer_codecs=(("deform/opacity", "vq/16"),))
    big = np.zeros(5000, np.float32)
    assert settings.codec_for("deform/opacity", big) == ("vq", 16)
    assert settings.codec_for("deform/log_scale", big) == ("q8", None)
    assert settings.codec_for("deform/opacity", np.zeros(10, np.float32)) == ("fp16", None)  # too small
    assert ExportSettings(gaussians="vq").codec_for("deform/rest_scale", big) == ("q16", None)  # keeps 16 bits
    assert not settings.lossless
    with pytest.raises(BundleError, match="buffer deform/opacity: unknown codec 'q5'"):
        ExportSettings(buffer_codecs=(("deform/opacity", "q5"),))
    with pytest.raises(BundleError, match="vq a number of entries"):
        ExportSettings(gaussians="vq/0")


def test_gt_export_takes_the_knobs(larger_avatar, tmp_path):
    from gaussiantalker.cli.export import app

    checkpoint = tmp_path / "avatar.ckpt"
    save_checkpoint(larger_avatar, checkpoint)
    out = tmp_path / "knobs.gtb"
    result = CliRunner().invoke(app, [str(checkpoint), "-o", str(out), "--spatial-order", "--deflate", "--quiet",
                                      "--buffer-codec", "deform/sh_dc=vq/32", "--midpoints"])
    assert result.exit_code == 0, result.output
    bundle = Bundle(out)
    assert bundle.manifest["buffers"]["deform/sh_dc"]["codec"]["name"] == "vq"
    assert bundle.manifest["export_settings"]["deflate"] is True
    bad = CliRunner().invoke(app, [str(checkpoint), "-o", str(out), "--buffer-codec", "deform/sh_dc"])
    assert bad.exit_code != 0 and "NAME=CODEC" in bad.output


def test_a_buffer_codec_for_a_buffer_the_bundle_lacks_is_refused(larger_avatar, tmp_path):
    """A misspelt name, or one of another rig's buffers, would change nothing: the export says so and writes
    nothing, naming the close match."""
    out = tmp_path / "misspelt.gtb"
    settings = ExportSettings(buffer_codecs=(("deform/rotations", "vq/256"),))
    with pytest.raises(BundleError, match=r"'deform/rotations' \(did you mean 'deform/rotation'"):
        export_bundle(larger_avatar, out, settings=settings, progress=False)
    assert not out.exists()
    settings = ExportSettings(buffer_codecs=(("deform/rotation", "vq/256"), ("flame/shapedirs", "q8")))
    with pytest.raises(BundleError, match=r"does not store: 'flame/shapedirs'\. Its buffers under 'flame/': none"):
        export_bundle(larger_avatar, out, settings=settings, progress=False)
    assert not out.exists()


def test_a_presets_own_buffer_codecs_are_not_asked_for(tmp_path):
    """compact's ARKit codecs name buffers a small avatar keeps inside its graph (arrays under 1 kB): the preset's
    own names are not checked, a caller's are."""
    tiny = import_lam(write_avatar_zip(tmp_path / "tiny.zip", AvatarSpec(rings=4, segments=6)), progress=False)
    result = export_bundle(tiny, tmp_path / "compact.gtb", preset="compact", progress=False)
    assert result.label == "compact"
    own = dict(get_preset("compact").export_for("arkit").buffer_codecs)
    assert any(name not in Bundle(result.path).manifest["buffers"] for name in own)  # the case this guards
