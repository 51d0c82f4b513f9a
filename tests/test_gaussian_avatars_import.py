"""GaussianAvatars avatars in: `gt-import gaussian-avatars` on avatar folders the tests write
(tests/gaussian_avatars.py) on a synthetic FLAME-layout model; the imported speaker against GaussianAvatars' own
formulas (an independent numpy implementation), its bundle against the torch speaker, its motion, an attached audio
model, and bad input."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from gaussian_avatars import (
    ga_flame_vertices,
    ga_flame_with_teeth,
    ga_world_gaussians,
    synthetic_flame,
    write_flame_npz,
    write_gaussian_avatar,
)
from typer.testing import CliRunner

from gaussiantalker.exporter.export.bundle_export import export_bundle
from gaussiantalker.exporter.export.checkpoint import load_checkpoint, save_checkpoint
from gaussiantalker.exporter.export.prune import prune_speaker
from gaussiantalker.exporter.imports.sources.gaussian_avatars import GaussianAvatarsOptions, import_gaussian_avatars
from gaussiantalker.exporter.imports.sources.gaussian_avatars_flame import load_gaussian_avatars_flame
from gaussiantalker.exporter.model.splat_math import quat_to_rotmat
from gaussiantalker.runtime import BundleError, DriveError, FlameMotion, HeadPose, TalkingHead
from gaussiantalker.sdk.errors import ImportFormatError
from gaussiantalker.sdk.image import psnr_db, to_uint8

ROOT = Path(__file__).resolve().parents[1]
# The contract's parity bound for 8-bit frames (runtime vs the torch speaker), and the for imported avatars.
MIN_PSNR_DB = 50.0
SIZE = (64, 64)
GAUSSIANS = 600
FRAMES = 6
# GaussianAvatars' formulas in float64 against the speaker's float32 torch path: centres agree to float32 rounding
# of coordinates ~0.1-1 m (a few 1e-8) amplified through LBS and the triangle frame; 1e-5 m (10 um) leaves 100x.
CENTRE_TOL_M = 1e-5
COV_RTOL = 1e-4


@pytest.fixture(scope="module")
def flame_model():
    return synthetic_flame(0)


@pytest.fixture(scope="module")
def avatar_dir(flame_model, tmp_path_factory):
    folder = tmp_path_factory.mktemp("ga")
    write_flame_npz(folder / "flame.npz", flame_model)
    written = write_gaussian_avatar(folder / "avatar", flame_model, n_gaussians=GAUSSIANS, frames=FRAMES)
    return folder, written


@pytest.fixture(scope="module")
def teeth_arrays(avatar_dir):
    """The synthetic FLAME with GaussianAvatars' teeth, loaded once for the tests that import many avatars."""
    return load_gaussian_avatars_flame(avatar_dir[0] / "flame.npz")


@pytest.fixture(scope="module")
def avatar(avatar_dir):
    folder, _ = avatar_dir
    return import_gaussian_avatars(folder / "avatar", folder / "flame.npz", GaussianAvatarsOptions(resolution=64))


@pytest.fixture(scope="module")
def avatar_bundle(avatar, tmp_path_factory):
    path = tmp_path_factory.mktemp("ga_bundle") / "avatar.gtb"
    export_bundle(avatar, path, progress=False)
    return path


def _deformed(speaker, drive):
    with torch.no_grad():
        means, cov3d, _, opacity = speaker.deform_drive(drive, torch.zeros(1, 3))
    return means[0].double().numpy(), cov3d[0].double().numpy(), opacity.double().numpy()


def _packed_covariance(scale: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """(xx, xy, xz, yy, yz, zz) of R diag(s^2) R^T from GaussianAvatars' world scale and (w, x, y, z) rotation."""
    rotation = quat_to_rotmat(torch.from_numpy(quat)).double().numpy()  # normalises; the stored q is unit already
    m = rotation * scale[:, None, :]
    cov = m @ m.transpose(0, 2, 1)
    return cov.reshape(-1, 9)[:, [0, 1, 2, 4, 5, 8]]


def test_import_follows_gaussian_avatars_formulas(avatar, avatar_dir, flame_model):
    """Every tracked frame: the speaker's centres, covariances and opacities are GaussianAvatars' (its FLAME with
    teeth and static offset, its triangle frame and size k), computed independently in numpy."""
    _, written = avatar_dir
    model, params, ply = ga_flame_with_teeth(flame_model), written["params"], written["ply"]
    assert avatar.config.binding == "scaled_triangle" and avatar.translator is None
    assert avatar.motion_track.shape == (FRAMES, 118) and avatar.gaussians.count == GAUSSIANS
    moved = []
    for frame in range(FRAMES):
        vertices = ga_flame_vertices(model, params, frame)
        xyz, scale, quat = ga_world_gaussians(vertices, model["f"], ply)
        means, cov3d, opacity = _deformed(avatar, avatar.motion_drive(frame))
        np.testing.assert_allclose(means, xyz, atol=CENTRE_TOL_M, rtol=0)
        expected = _packed_covariance(scale, quat)
        np.testing.assert_allclose(cov3d, expected, atol=COV_RTOL * np.abs(expected).max(), rtol=0)
        np.testing.assert_allclose(opacity, 1 / (1 + np.exp(-ply["opacity"].astype(np.float64))), atol=1e-6)
        moved.append(xyz)
    assert np.abs(moved[-1] - moved[0]).max() > 1e-3  # the tracked motion really moves the Gaussians


def test_checkpoint_round_trip(avatar, tmp_path):
    loaded = load_checkpoint(save_checkpoint(avatar, tmp_path / "avatar.ckpt"))
    assert loaded.translator is None and loaded.config == avatar.config and loaded.source == avatar.source
    torch.testing.assert_close(loaded.motion_track, avatar.motion_track)
    drive = avatar.motion_drive(3)
    np.testing.assert_array_equal(_deformed(loaded, drive)[0], _deformed(avatar, drive)[0])


def test_pruned_avatar_keeps_its_binding(avatar):
    """A Gaussian budget (the compact, fast and mobile presets) keeps GaussianAvatars' scaled_triangle binding: the
    kept Gaussians deform exactly as they did in the whole avatar."""
    keep = (torch.arange(avatar.gaussians.count) % 3 != 0).numpy()
    pruned = prune_speaker(avatar, int(keep.sum()), torch.from_numpy(keep.astype(np.float64)))
    assert pruned.gaussians.binding == "scaled_triangle" and pruned.gaussians.count == int(keep.sum())
    drive = avatar.motion_drive(FRAMES - 1)
    whole, kept = _deformed(avatar, drive), _deformed(pruned, drive)
    for part in range(3):
        np.testing.assert_array_equal(kept[part], whole[part][keep])


def test_bundle_plays_its_motion_like_torch(avatar, avatar_bundle):
    """The runtime's frames of the avatar's own motion and of FLAME drives against the torch speaker: 50 dB; the
    bundle holds no translator, no latent-pose product, and its tracked motion."""
    with TalkingHead(avatar_bundle, resolution=SIZE) as head:
        assert head.driver.rig == "flame" and not head.driver.has_translator
        assert head.bundle.manifest["speaker"]["binding"] == "scaled_triangle"
        assert head.bundle.manifest["driver"] == "flame" and head.bundle.manifest["source"]["format"] == \
            "gaussian-avatars"
        assert not any(name.startswith("deform/latent_pose") or name == "deform/latent_weight"
                       for name in head.bundle.manifest["buffers"])
        motion = head.driver.motion_track
        assert isinstance(motion, FlameMotion) and len(motion) == FRAMES
        drives = list(head.drives())
        frames = list(head.frames(output="float"))
        assert len(frames) == FRAMES
        for index in (0, FRAMES - 1):
            reference = avatar.render(drives[index], head.camera, head.frame_renderer.background).numpy()
            assert psnr_db(to_uint8(reference), to_uint8(frames[index])) >= MIN_PSNR_DB, index
        params = head.render_params(jaw_pose=[0.3, 0, 0], head_rotation=[0, 0.4, 0], output="float")
        reference = avatar.render(drives[0].__class__.make(100, jaw_pose=[0.3, 0, 0],
                                                           head_pose=HeadPose.make([0, 0.4, 0])),
                                  head.camera, head.frame_renderer.background).numpy()
        assert psnr_db(to_uint8(reference), to_uint8(params)) >= MIN_PSNR_DB
        with pytest.raises(BundleError, match="imported avatar without an audio model"):
            list(head.frames(np.zeros(16000, np.float32), 16000))
        with pytest.raises(DriveError, match="JSON motion holds ARKit weights"):
            head.driver.motion("bsData.json")
        with pytest.raises(DriveError, match="FLAME parameters.*a drive of the 52 ARKit"):
            head.render_blendshapes({"jawOpen": 1.0})


def test_motion_npz_and_table(avatar_bundle, avatar_dir, tmp_path):
    """A motion npz of GaussianAvatars' keys (at another fps: resampled), a [T, E + 18] table, a bad npz."""
    _, written = avatar_dir
    params = {k: v for k, v in written["params"].items() if k not in ("shape", "static_offset", "dynamic_offset")}
    path = tmp_path / "motion.npz"
    np.savez(path, **params)
    with TalkingHead(avatar_bundle, resolution=SIZE) as head:
        np.testing.assert_allclose(head.driver.motion(path).table, head.driver.motion_track.table, atol=1e-6)
        table = head.driver.motion_track.table[:2]
        assert len(list(head.drives(motion=table))) == 2
        half = {k: v[::2] for k, v in params.items()}
        np.savez(path, **half)
        assert len(head.driver.motion(FlameMotion.from_table(np.concatenate(
            [half["expr"], half["rotation"], half["neck_pose"], half["jaw_pose"], half["eyes_pose"],
             half["translation"]], 1), 12.5))) == 6  # 3 frames at 12.5 fps play 6 at 25
        np.savez(path, **{**params, "jaw_pose": params["jaw_pose"][:-1]})
        with pytest.raises(DriveError, match=r"'jaw_pose' has shape \[5, 3\], expected \[6, 3\]"):
            head.driver.motion(path)
        np.savez(path, **{k: v for k, v in params.items() if k != "eyes_pose"})
        with pytest.raises(DriveError, match="missing eyes_pose"):
            head.driver.motion(path)


def _flame_audio_model(path: Path, n_expr: int = 100, frame_samples: int = 640, gain: float = 4.0) -> Path:
    """A tiny audio-to-FLAME ONNX model (onnx.helper): jaw pose x = gain x mean |audio| per `frame_samples` block,
    expression coefficient 0 = the same, everything else 0; outputs [1, T, n_expr] and [1, T, 3]."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    def kernel(width: int) -> np.ndarray:
        k = np.zeros((width, 1, frame_samples), np.float32)
        k[0, 0, :] = gain / frame_samples
        return k

    nodes = [helper.make_node("Abs", ["pcm"], ["level"]),
             helper.make_node("Unsqueeze", ["level", "axis1"], ["level3"])]
    for name in ("expr", "jaw"):
        nodes += [helper.make_node("Conv", ["level3", f"k_{name}"], [f"{name}_c"], strides=[frame_samples]),
                  helper.make_node("Transpose", [f"{name}_c"], [f"{name}_out"], perm=[0, 2, 1])]
    graph = helper.make_graph(
        nodes, "energy", [helper.make_tensor_value_info("pcm", TensorProto.FLOAT, [1, "samples"])],
        [helper.make_tensor_value_info("expr_out", TensorProto.FLOAT, [1, "frames", n_expr]),
         helper.make_tensor_value_info("jaw_out", TensorProto.FLOAT, [1, "frames", 3])],
        [numpy_helper.from_array(kernel(n_expr), "k_expr"), numpy_helper.from_array(kernel(3), "k_jaw"),
         numpy_helper.from_array(np.array([1], np.int64), "axis1")])
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), str(path))
    return path


def test_cli_import_export_verify_play_and_audio_model(avatar_dir, tmp_path):
    """The user's path: gt-import gaussian-avatars (with an attached audio-to-FLAME model), gt-export --verify (the
    bundle's frames and novel views against the torch speaker), play.py --motion, and audio through the model."""
    from gaussiantalker.cli.export import app as export_app
    from gaussiantalker.cli.imports import app as import_app
    from gaussiantalker.exporter.imports.audio_model import flame_outputs, load_audio_model

    folder, _ = avatar_dir
    runner = CliRunner()
    with pytest.raises(ImportFormatError, match=r"output 'expr_out' must be float32 \[1, T, 100\] expression.*50"):
        load_audio_model(_flame_audio_model(tmp_path / "a2f_50.onnx", n_expr=50), flame_outputs(100))
    model = _flame_audio_model(tmp_path / "a2f.onnx")
    checkpoint, bundle = tmp_path / "a.ckpt", tmp_path / "a.gtb"
    result = runner.invoke(import_app, ["gaussian-avatars", str(folder / "avatar"), "--flame",
                                        str(folder / "flame.npz"), "-o", str(checkpoint), "--audio-model", str(model)])
    assert result.exit_code == 0, result.output
    assert f"imported {GAUSSIANS} Gaussians (SH degree 3)" in result.output and "a2f.onnx attached" in result.output
    result = runner.invoke(export_app, [str(checkpoint), "-o", str(bundle), "--verify", "--frames", "3",
                                        "--resolution", "48", "-q"])
    assert result.exit_code == 0 and "verification PASSED" in result.output, result.output
    assert "translator       0.000e+00" in result.output  # the bundle's graph is the attached model, exactly
    assert "novel views: 3 cameras" in result.output
    sys.path.insert(0, str(ROOT / "samples"))
    try:
        from play import OWN_MOTION, _own_motion_flag
        from play import app as play_app
    finally:
        sys.path.pop(0)
    assert _own_motion_flag(["a.gtb", "--motion", "-q"]) == ["a.gtb", "--motion", OWN_MOTION, "-q"]
    video = tmp_path / "talk.mp4"
    result = runner.invoke(play_app, [str(bundle), "-o", str(video), "-r", "48", "--motion", OWN_MOTION, "-q"])
    assert result.exit_code == 0 and f"{FRAMES} frames" in result.output, result.output
    rate = 16000
    loud = (0.5 * np.sin(2 * np.pi * 220 * np.arange(rate) / rate)).astype(np.float32)
    audio = np.concatenate([np.zeros(rate // 2, np.float32), loud])
    with TalkingHead(bundle, resolution=(48, 48)) as head:
        expression, jaw = head.driver.translate(audio)
        assert expression.shape == (38, 100) and jaw[:10, 0].max() < 1e-6 and jaw[20:, 0].min() > 0.5
        frames = list(head.frames(audio, rate))
        assert len(frames) == 38 and not np.array_equal(frames[0], frames[30])


def test_cli_import_attaches_the_builtin_voice(avatar_dir, tmp_path):
    """Without --audio-model, gt-import gaussian-avatars attaches the built-in FLAME voice driver, its expressions
    fitted on the user's FLAME (docs/voice.md): speech opens the jaw and moves the expression, silence does not."""
    from gaussiantalker.cli.export import app as export_app
    from gaussiantalker.cli.imports import app as import_app
    from gaussiantalker.sdk.audio import load_audio

    folder, _ = avatar_dir
    runner = CliRunner()
    checkpoint, bundle = tmp_path / "a.ckpt", tmp_path / "a.gtb"
    result = runner.invoke(import_app, ["gaussian-avatars", str(folder / "avatar"), "--flame",
                                        str(folder / "flame.npz"), "-o", str(checkpoint)])
    assert result.exit_code == 0 and "built-in voice driver attached" in result.output, result.output
    result = runner.invoke(export_app, [str(checkpoint), "-o", str(bundle), "-q"])
    assert result.exit_code == 0, result.output
    speech = load_audio(ROOT / "tests" / "data" / "voice_heldout.wav", 16000)
    audio = np.concatenate([np.zeros(16000, np.float32), speech])  # 1 s of silence, then the sentence
    with TalkingHead(bundle, resolution=(48, 48)) as head:
        expression, jaw = head.driver.translate(audio)
        assert expression.shape == (len(audio) // 640 + (len(audio) % 640 > 0), 100)
        assert np.abs(jaw[:20]).max() < 0.02 and jaw[25:, 0].max() > 0.1  # radians: the jaw opens with speech
        assert np.abs(expression[:20]).max() < 0.1 and np.abs(expression[25:]).max() > 0.1


@pytest.mark.parametrize("case, words", [
    ("no_binding", "lacks field binding_0"),
    ("binding_outside", "binding_0 of Gaussian 0 is 10144.0, not a triangle of the mesh [0, 10144)"),
    ("binding_fraction", "binding_0 of Gaussian 0 is 2.5"),
    ("no_opacity", "lacks field(s) opacity"),
    ("expr_50", "'expr' has 50 coefficients per frame; GaussianAvatars tracks 100"),
    ("static_offset", "'static_offset' has shape [1, 5023, 3], expected [1, 5143, 3]"),
    ("no_shape", "'shape' must be 300 finite FLAME shape coefficients, got missing"),
    ("short_rotation", "'rotation' has shape [5, 3], expected [6, 3]"),
])
def test_bad_avatars_name_the_field(flame_model, teeth_arrays, tmp_path, case, words):
    edits = {
        "no_binding": {"drop_fields": ["binding_0"]},
        "no_opacity": {"drop_fields": ["opacity"]},
        "no_shape": {"drop_fields": ["shape"]},
        "binding_outside": {"edit_ply": lambda p: p["binding_0"].__setitem__(0, 10144.0)},
        "binding_fraction": {"edit_ply": lambda p: p["binding_0"].__setitem__(0, 2.5)},
        "expr_50": {"edit_params": lambda p: {**p, "expr": p["expr"][:, :50]}},
        "static_offset": {"edit_params": lambda p: {**p, "static_offset": p["static_offset"][:, :5023]}},
        "short_rotation": {"edit_params": lambda p: {**p, "rotation": p["rotation"][:-1]}},
    }
    write_gaussian_avatar(tmp_path / "bad", flame_model, n_gaussians=20, frames=FRAMES, **edits[case])
    with pytest.raises(ImportFormatError) as error:
        import_gaussian_avatars(tmp_path / "bad", teeth_arrays)
    assert words in str(error.value)


def test_missing_folders_and_iterations(flame_model, teeth_arrays, tmp_path):
    with pytest.raises(ImportFormatError, match="no such directory"):
        import_gaussian_avatars(tmp_path / "missing", teeth_arrays)
    (tmp_path / "empty").mkdir()
    with pytest.raises(ImportFormatError, match="no point_cloud/iteration_N/point_cloud.ply"):
        import_gaussian_avatars(tmp_path / "empty", teeth_arrays)
    write_gaussian_avatar(tmp_path / "two", flame_model, n_gaussians=20, frames=2, iteration=100)
    write_gaussian_avatar(tmp_path / "two", flame_model, n_gaussians=30, frames=2, iteration=2000)
    arrays = teeth_arrays
    assert import_gaussian_avatars(tmp_path / "two", arrays).gaussians.count == 30  # the last iteration
    assert import_gaussian_avatars(tmp_path / "two", arrays, GaussianAvatarsOptions(iteration=100)).gaussians.count \
        == 20
    with pytest.raises(ImportFormatError, match="no iteration 7; it has 100, 2000"):
        import_gaussian_avatars(tmp_path / "two", arrays, GaussianAvatarsOptions(iteration=7))
    (tmp_path / "two/point_cloud/iteration_2000/flame_param.npz").unlink()
    with pytest.raises(ImportFormatError, match="flame_param.npz is missing"):
        import_gaussian_avatars(tmp_path / "two", arrays)


def test_scene_needs_a_trained_translator(avatar, tmp_path):
    from gaussiantalker.sdk.scene import load_scene

    with pytest.raises(BundleError, match="scene specialisation .* needs the speaker's trained translator"):
        export_bundle(avatar, tmp_path / "scene.gtb", progress=False,
                      scene=load_scene(ROOT / "samples" / "front_scene.toml"))


@pytest.mark.parametrize("yaw, pitch", [(90.0, 0.0), (-35.0, 0.0), (0.0, 20.0), (30.0, -15.0)])
def test_novel_view_cameras_swing_around_the_head(yaw, pitch):
    """`Camera.orbited` (verify's novel views): same distance and intrinsics, the target still at the principal
    point, the eye turned by the asked angles about the camera's own up and right axes."""
    from gaussiantalker.sdk.camera import Camera

    target = np.array([0.01, 0.02, -0.03])
    camera = Camera.looking_at(target + [0.0, 0.0, 1.0], target, (0.0, 1.0, 0.0), 64, 48, 20.0)
    view = camera.orbited(yaw, pitch, target)
    assert np.linalg.norm(view.center - target) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(view.R @ view.R.T, np.eye(3), atol=1e-12)
    p = view.R @ target + view.t
    assert p[2] > 0 and np.allclose(p[:2], 0.0, atol=1e-12)  # the target is dead ahead
    offset = view.center - target
    assert np.degrees(np.arctan2(offset[0], offset[2])) == pytest.approx(yaw, abs=1e-9)
    assert np.degrees(np.arcsin(-offset[1])) == pytest.approx(pitch, abs=1e-9)
