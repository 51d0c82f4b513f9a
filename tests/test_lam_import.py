"""LAM avatars in: `gt-import lam` on avatar zips the tests write (tests/lam_avatars.py), the ARKit speaker's
torch reference against the format's own maths, its bundle against the torch speaker, and every bad input."""

from __future__ import annotations

import json
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from ci_tools import need_module
from lam_avatars import AvatarSpec, expected_centres, gaussians, motion_json, write_avatar_zip
from typer.testing import CliRunner

from gaussiantalker.exporter.export.bundle_export import export_bundle
from gaussiantalker.exporter.export.checkpoint import load_checkpoint, save_checkpoint
from gaussiantalker.exporter.imports.sources.lam import LAM_WEIGHT_SCALE, LamOptions, import_lam, rotation_vector
from gaussiantalker.runtime import DriveError, HeadPose, TalkingHead
from gaussiantalker.sdk.bundle import Bundle
from gaussiantalker.sdk.drive import BlendshapeDrive
from gaussiantalker.sdk.errors import ImportFormatError
from gaussiantalker.sdk.image import psnr_db, to_uint8
from gaussiantalker.sdk.numerics import SH_C0
from gaussiantalker.sdk.rig import ARKIT_BLENDSHAPES

# Frames of the small avatar: the runtime against the torch reference rasterizer. The contract's parity bound.
MIN_PSNR_DB = 50.0
SIZE = (96, 128)
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def avatar_zip(tmp_path_factory):
    return write_avatar_zip(tmp_path_factory.mktemp("lam") / "avatar.zip")


@pytest.fixture(scope="module")
def avatar(avatar_zip):
    return import_lam(avatar_zip, progress=False)


@pytest.fixture(scope="module")
def avatar_bundle(avatar, tmp_path_factory):
    path = tmp_path_factory.mktemp("lam_bundle") / "avatar.gtb"
    export_bundle(avatar, path, progress=False)
    return path


def _centres(speaker, drive: BlendshapeDrive) -> np.ndarray:
    with torch.no_grad():
        means, _, _, _ = speaker.deform_drive(drive, torch.zeros(1, 3))
    return means[0].numpy()


def test_import_places_gaussians_as_lam_renderer(avatar):
    """Vertex + morphs (with the renderer's weight scales) + offset, carried by the head bone: the format's maths."""
    spec = AvatarSpec()
    assert avatar.gaussians.count == spec.rings * spec.segments
    rest = _centres(avatar, BlendshapeDrive.make())
    np.testing.assert_allclose(rest, expected_centres(spec, {}), atol=1e-6)
    weights = {"jawOpen": 0.7, "eyeBlinkLeft": 1.0, "mouthSmileLeft": 0.4}
    scaled = {name: w * LAM_WEIGHT_SCALE.get(name, 1.0) for name, w in weights.items()}
    # Pose track frame 15 is t = 0.5 s of the idle clip: the head bone turned 0.3 rad about its local x.
    row = avatar.pose_track[15].numpy()
    posed = _centres(avatar, BlendshapeDrive.make(weights, HeadPose.make(row[:3], row[3:])))
    expected = expected_centres(spec, scaled, 0.3)
    assert np.abs(expected - expected_centres(spec, scaled, 0.0)).max() > 0.02  # the head really moved
    np.testing.assert_allclose(posed, expected, atol=1e-6)


def test_import_reads_tracks_and_records_source(avatar):
    assert avatar.source["pose_clip"] == "idle"
    assert avatar.pose_track.shape == (31, 6)  # 1 s of clip at 30 fps, both ends
    np.testing.assert_allclose(avatar.pose_track[0].numpy(), 0.0, atol=1e-6)
    motion = motion_json()
    assert avatar.motion_track.shape == (len(motion["frames"]), len(ARKIT_BLENDSHAPES))
    np.testing.assert_allclose(avatar.motion_track.numpy(), [f["weights"] for f in motion["frames"]], atol=1e-6)
    assert avatar.source["morph_targets"] == ["jawOpen", "eyeBlinkLeft", "mouthSmileLeft", "browInnerUp"]


def test_raw_weights_and_other_clip(avatar_zip):
    raw = import_lam(avatar_zip, LamOptions(clip="speak", renderer_weight_scale=False), progress=False)
    spec = AvatarSpec()
    centres = _centres(raw, BlendshapeDrive.make({"jawOpen": 0.7}))
    np.testing.assert_allclose(centres, expected_centres(spec, {"jawOpen": 0.7}), atol=1e-6)
    assert raw.source["pose_clip"] == "speak" and raw.pose_track.shape[0] == 7  # 0.2 s at 30 fps
    np.testing.assert_allclose(np.linalg.norm(raw.pose_track[-1, :3].numpy()), 0.2, atol=1e-5)


def test_members_at_top_level_and_colours(tmp_path):
    spec = AvatarSpec(folder=None, motion=False)
    speaker = import_lam(write_avatar_zip(tmp_path / "top.zip", spec), progress=False)
    assert speaker.motion_track is None

    # f_dc is RGB, stored in 8 bits by the renderer: SH degree 0 round-trips it; opacity also 8 bits.
    rgb = speaker.gaussians.sh[:, 0].detach().numpy() * SH_C0 + 0.5
    np.testing.assert_allclose(rgb, np.floor(gaussians(spec)["f_dc"] * 255) / 255, atol=1e-6)
    opacity = torch.sigmoid(speaker.gaussians.opacity_logit).detach().numpy()
    np.testing.assert_allclose(opacity, np.floor(255 / (1 + np.exp(-gaussians(spec)["opacity"]))) / 255, atol=1e-6)
    exact = import_lam(tmp_path / "top.zip", LamOptions(renderer_colours=False), progress=False)
    np.testing.assert_allclose(exact.gaussians.sh[:, 0].detach().numpy() * SH_C0 + 0.5, gaussians(spec)["f_dc"],
                               atol=1e-6)


@pytest.mark.parametrize("spec, member, words", [
    (AvatarSpec(skip=("offset.ply",)), "offset.ply", "lacks"),
    (AvatarSpec(skip=("skin.glb",)), "skin.glb", "lacks"),
    (AvatarSpec(skip=("morphs",)), "skin.glb", "morph targets"),
    (AvatarSpec(skip=("skin",)), "skin.glb", "no skin"),
    (AvatarSpec(vertex_order_length=5), "vertex_order.json", "5 entries"),
    (AvatarSpec(extra_names=("tongueOutX",)), "skin.glb", "'tongueOutX'"),
    (AvatarSpec(skip=("ply_field",)), "offset.ply", "opacity"),
])
def test_bad_avatars_name_the_member(tmp_path, spec, member, words):
    path = write_avatar_zip(tmp_path / "bad.zip", spec)
    with pytest.raises(ImportFormatError) as info:
        import_lam(path, progress=False)
    assert member in str(info.value) and words in str(info.value), str(info.value)


def test_bad_zips(tmp_path):
    path = tmp_path / "two.zip"
    good = write_avatar_zip(tmp_path / "one.zip")
    with zipfile.ZipFile(good) as source, zipfile.ZipFile(path, "w") as target:
        for info in source.infolist():
            target.writestr(info.filename, source.read(info))
            target.writestr("second/" + info.filename.split("/")[-1], source.read(info))
    with pytest.raises(ImportFormatError, match="several folders"):
        import_lam(path, progress=False)
    (tmp_path / "not.zip").write_bytes(b"not a zip")
    with pytest.raises(ImportFormatError, match="not a readable zip"):
        import_lam(tmp_path / "not.zip", progress=False)
    with pytest.raises(ImportFormatError, match="no clip named 'dance'"):
        import_lam(good, LamOptions(clip="dance"), progress=False)


def test_truncated_glb(tmp_path):
    from gaussiantalker.exporter.imports.formats.gltf import load_glb

    data = zipfile.ZipFile(write_avatar_zip(tmp_path / "a.zip")).read("avatar/skin.glb")
    with pytest.raises(ImportFormatError, match="skin.glb: glTF version 2 with length"):
        load_glb(data[: len(data) // 2], "skin.glb")
    with pytest.raises(ImportFormatError, match="not a binary glTF"):
        load_glb(b"GLTF" + data[4:], "skin.glb")


def test_rotation_vector_round_trips():
    from lam_avatars import axis_angle_quat, quat_matrix

    rng = np.random.default_rng(0)
    for angle in (0.0, 1e-8, 0.3, 2.0, np.pi - 1e-6, np.pi):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        vector = rotation_vector(quat_matrix(axis_angle_quat(axis, angle)))
        np.testing.assert_allclose(quat_matrix(axis_angle_quat(vector if angle else axis, np.linalg.norm(vector))),
                                   quat_matrix(axis_angle_quat(axis, angle)), atol=1e-6)


def test_checkpoint_round_trip(avatar, tmp_path):
    path = save_checkpoint(avatar, tmp_path / "avatar.ckpt")
    loaded = load_checkpoint(path)
    drive = BlendshapeDrive.make({"jawOpen": 0.5}, HeadPose.make([0.1, 0.2, 0.0]))
    np.testing.assert_array_equal(_centres(loaded, drive), _centres(avatar, drive))
    assert loaded.source == avatar.source and loaded.config == avatar.config


def test_bundle_matches_torch(avatar, avatar_bundle):
    """Runtime frames of random ARKit drives against the torch reference rasterizer: the contract's 50 dB."""
    with TalkingHead(avatar_bundle, resolution=SIZE) as head:
        assert head.driver.rig == "arkit" and head.fps == 30 and head.driver.motion_track is not None
        rng = np.random.default_rng(1)
        for index in range(3):
            weights = dict(zip(ARKIT_BLENDSHAPES, rng.uniform(0, 1, 52) * (rng.random(52) < 0.3), strict=True))
            pose = HeadPose.make(rng.normal(0, 0.15, 3), rng.normal(0, 0.01, 3))
            frame = head.render_blendshapes(weights, pose, output="float")
            reference = avatar.render(head.driver.drive(weights, pose), head.camera,
                                      head.frame_renderer.background).numpy()
            assert psnr_db(to_uint8(reference), to_uint8(frame)) >= MIN_PSNR_DB, index
        assert head.render_blendshapes(np.zeros(52)).shape == (SIZE[1], SIZE[0], 3)
        assert head.render_blendshapes(output="rgba").shape == (SIZE[1], SIZE[0], 4)


def test_motion_frames_and_drive_mismatch(avatar_bundle, small_export, tmp_path):
    with TalkingHead(avatar_bundle, resolution=SIZE) as head:
        frames = list(head.frames())
        assert len(frames) == len(head.driver.motion_track) and not np.array_equal(frames[0], frames[3])
        motion = tmp_path / "motion.json"
        motion.write_text(json.dumps(motion_json(frames=6, fps=15.0)))
        assert len(list(head.frames(motion=motion))) == 12  # 6 frames at 15 fps play 12 frames at 30 fps
        with pytest.raises(DriveError, match="ARKit blendshape weights.*use render_blendshapes"):
            head.render_params(jaw_pose=[0.2, 0, 0])
        with pytest.raises(DriveError, match="no audio model"):
            list(head.frames(np.zeros(16000, np.float32), 16000))
        with pytest.raises(DriveError, match="unknown blendshape name 'jawopen'"):
            head.render_blendshapes({"jawopen": 1.0})
    with TalkingHead(small_export.path, resolution=(64, 64)) as flame_head:
        with pytest.raises(DriveError, match="FLAME parameters.*a drive of the 52 ARKit"):
            flame_head.render_blendshapes({"jawOpen": 1.0})
        with pytest.raises(DriveError, match="FLAME parameters"):
            flame_head.render(BlendshapeDrive.make())


def test_cli_import_export_verify_play(avatar_zip, tmp_path):
    """gt-import lam (the built-in voice attached by default), gt-export --verify --preset balanced, then play.py
    --motion and --audio: the user's path; --no-voice imports without an audio model."""
    from gaussiantalker.cli.export import app as export_app
    from gaussiantalker.cli.imports import app as import_app

    runner = CliRunner()
    checkpoint = tmp_path / "avatar.ckpt"
    result = runner.invoke(import_app, ["lam", str(avatar_zip), "-o", str(checkpoint), "-q"])
    assert result.exit_code == 0, result.output
    assert "imported 96 Gaussians, 4 morph targets" in result.output
    assert "built-in voice driver attached" in result.output
    bundle = tmp_path / "avatar.gtb"
    result = runner.invoke(export_app, [str(checkpoint), "-o", str(bundle), "--verify", "--frames", "3",
                                        "--resolution", "64", "--preset", "balanced", "-q"])
    assert result.exit_code == 0, result.output
    assert "not compared" not in result.output  # the attached voice model is verified like any translator
    assert "verification PASSED" in result.output
    sys.path.insert(0, str(ROOT / "samples"))
    try:
        from play import app as play_app
    finally:
        sys.path.pop(0)
    video = tmp_path / "avatar.mp4"
    result = runner.invoke(play_app, [str(bundle), "-o", str(video), "-r", "64", "-q"])
    assert result.exit_code == 0, result.output
    assert "12 frames, 0.4 s, no audio" in result.output and video.stat().st_size > 0
    result = runner.invoke(play_app, [str(bundle), "-o", str(video), "-r", "48", "-q", "--audio",
                                      str(ROOT / "tests" / "data" / "voice_heldout.wav")])
    assert result.exit_code == 0, result.output
    assert "141 frames, 4.7 s" in result.output and video.stat().st_size > 0, result.output
    bare = tmp_path / "bare.ckpt"
    result = runner.invoke(import_app, ["lam", str(avatar_zip), "-o", str(bare), "-q", "--no-voice"])
    assert result.exit_code == 0 and "no audio model (--no-voice)" in result.output, result.output
    assert load_checkpoint(bare).audio_model is None
    result = runner.invoke(import_app, ["lam", str(avatar_zip), "-o", str(bare), "--no-voice", "--audio-model",
                                        str(bare)])
    assert result.exit_code == 2 and "not both" in result.output
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"names": ["jawOpen", "smile"], "frames": [{"weights": [0, 1]}]}))
    result = runner.invoke(play_app, [str(bundle), "-o", str(video), "--motion", str(bad), "-q"])
    assert result.exit_code == 2 and "unknown blendshape name 'smile'" in result.output
    result = runner.invoke(import_app, ["lam", str(tmp_path / "missing.zip")])
    assert result.exit_code == 2 and "does not exist" in result.output


def test_audio_model_drives_the_avatar(avatar_zip, tmp_path):
    """An attached audio-to-ARKit model: checked and renamed at import, carried into the bundle as its translator
    graph, verified against the model file, and audio then drives the avatar (loud: jaw open, silent: neutral)."""
    from lam_avatars import energy_audio_model

    from gaussiantalker.cli.export import app as export_app
    from gaussiantalker.cli.imports import app as import_app
    from gaussiantalker.exporter.imports.audio_model import load_audio_model

    bad = energy_audio_model(tmp_path / "bad.onnx", width=10)
    with pytest.raises(ImportFormatError, match=r"must be float32 \[1, T, 52\].*10"):
        load_audio_model(bad)
    model = energy_audio_model(tmp_path / "energy.onnx")
    runner = CliRunner()
    checkpoint, bundle = tmp_path / "a.ckpt", tmp_path / "a.gtb"
    result = runner.invoke(import_app, ["lam", str(avatar_zip), "-o", str(checkpoint), "--audio-model", str(model),
                                        "-q"])
    assert result.exit_code == 0 and "audio model energy.onnx attached" in result.output, result.output
    assert load_checkpoint(checkpoint).audio_model == load_audio_model(model)
    result = runner.invoke(export_app, [str(checkpoint), "-o", str(bundle), "--verify", "--frames", "2",
                                        "--resolution", "48", "-q"])
    assert result.exit_code == 0 and "verification PASSED" in result.output, result.output
    assert "translator       0.000e+00" in result.output  # the bundle's graph is the attached model, exactly
    rate = 16000
    t = np.arange(rate) / rate
    loud = (0.5 * np.sin(2 * np.pi * 220 * t)).astype(np.float32)
    audio = np.concatenate([np.zeros(rate // 2, np.float32), loud])  # 1.5 s: silence, then a loud tone
    with TalkingHead(bundle, resolution=(48, 48)) as head:
        weights = head.driver.translate(audio)
        assert weights.shape == (45, 52)  # 1.5 s at 30 fps, though the model gives floor(S / 533) = 45 frames
        jaw = weights[:, ARKIT_BLENDSHAPES.index("jawOpen")]
        assert jaw[:10].max() < 1e-6 and jaw[20:40].min() > 0.5 * 8 * 2 / np.pi * 0.9, jaw
        frames = list(head.frames(audio, rate))
        assert len(frames) == 45 and not np.array_equal(frames[0], frames[30])
        video = head.write_video(tmp_path / "talk.mp4", audio, rate)
        assert video.stat().st_size > 0


def test_mnn_graphs_and_scene_refusal(avatar, tmp_path):
    """An ARKit speaker's bundle with MNN graphs verifies like a FLAME one (MNN vs onnxruntime, frames vs torch);
    a scene is refused with a clear error (scenes are for FLAME speakers)."""
    from gaussiantalker.exporter.verify.bundle_verify import verify_bundle
    from gaussiantalker.sdk.errors import BundleError
    from gaussiantalker.sdk.scene import load_scene

    need_module("MNN", "mnn")
    path = tmp_path / "mnn.gtb"
    export_bundle(avatar, path, progress=False, mnn=True)
    report = verify_bundle(avatar, path, frames=2, resolution=(48, 48), progress=False)
    assert report["passed"] and report["mnn"]["passed"], report
    with pytest.raises(BundleError, match="scene specialisation .* is for FLAME speakers"):
        export_bundle(avatar, tmp_path / "scene.gtb", progress=False, scene=load_scene(
            ROOT / "samples" / "front_scene.toml"))


def test_morph_targets_keep_8_bits_in_reduced_presets():
    """4-bit morph targets cost 12 dB of head PSNR on LAM's sample avatar (presets.KEEP_8_BITS): a quantised
    preset stores them with at least 8 bits, in the preset's chunks; the FLAME bases keep the preset's codec."""
    from gaussiantalker.exporter.export.presets import get_preset

    morphs = np.zeros((51, 60_000), np.float32)
    for name in ("balanced", "compact", "fast"):
        settings = get_preset(name).export
        flame = settings.codec_for("deform/blend_basis", morphs)
        assert flame[0] == "q4" and settings.codec_for("deform/morph_basis", morphs) == ("q8", flame[1]), name
    assert get_preset("mobile").export.codec_for("deform/morph_basis", morphs) == ("fp16", None)


def test_a_mostly_zero_morph_basis_is_stored_sparse(avatar_bundle):
    """The morph basis is stored sparse (a bitmask and the nonzero values, sdk/codecs.py) when at least half of it
    is zeros, as an avatar's blendshapes each moving one region of the face make it; it decodes to the same basis,
    which test_bundle_matches_torch renders. Other buffers and dense bases stay dense."""
    from gaussiantalker.exporter.export.presets import stored_sparse

    bundle = Bundle(avatar_bundle)
    basis = bundle.buffer("deform/morph_basis")
    zeros = 1 - np.count_nonzero(basis) / basis.size
    assert ("sparse" in bundle.manifest["buffers"]["deform/morph_basis"]["codec"]) == (zeros >= 0.5), zeros
    regional = np.zeros((51, 6000), np.float32)
    regional[:, :1200] = 1.0  # 80% zeros
    assert stored_sparse("deform/morph_basis", regional)
    assert not stored_sparse("deform/morph_basis", np.ones((51, 6000), np.float32))
    assert not stored_sparse("deform/blend_basis", regional)
    assert not stored_sparse("deform/morph_basis", np.zeros((0, 6000), np.float32))
