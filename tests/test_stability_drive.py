"""Deformation stage at extreme drive and geometry: torch speaker vs exported `deform` graph vs runtime frames.

Every case checks: no NaN/Inf in any graph output (torch and onnxruntime) or pixel; graph outputs agree; the GL
frame agrees with the torch reference frame. Each case's observed numbers go into the stability table.

Bounds, and why:
* Graph outputs: max |onnx - torch| <= rtol * max |torch| per output (the output's own scale, so cov3d ~1e-5 m^2
  is not judged against 1), rtol = 1e-4 + ANGLE_ULPS * 2^-24 * theta, theta the largest joint rotation angle.
  The 1e-4 is the project's fp32 graph bound (different float32 kernels, a few ulps per op over ~100 ops). The
  second term is conditioning, not drift: both sides reduce |r|^2 in float32 in different orders, so the angle
  of a rotation vector of length theta differs by ~theta * 2^-23 between them, which turns every point about its
  joint by that angle (lever arm <= the output scale). It is 6e-6 at theta = 4 pi and 8e-3 at the drive limit
  (1e4 rad per component, |r| = 1.7e4); measured up to 0.4 of that. Collapsed triangles get no looser bound:
  the frame's guards fade a collapsing axis continuously (`gaussians.FRAME_DEGENERATE_FRACTION`), so rounding
  noise in the vertices moves the frame by noise / tolerance, not by up to 2.
* Frames (float, 64 x 64): PSNR >= 60 dB, the project's torch-vs-GL parity bound. What remains is GL edge
  pixels (quad snapping, ~1% of an opacity) and float reassociation in the projection. For rotation vectors far
  beyond 4 pi the two sides' Gaussians differ by the conditioning term above (up to ~2 px of motion of splats
  whose colour is then ~30), so there the runtime splats the torch Gaussians: the frame check isolates the
  splatter, the graph check the deformation.
* Scaled heads (torch only, any scale): outputs equal the unscaled head's (means / s, cov3d / s^2) within 1e-4 of
  the output scale, frames within 60 dB: scaling FLAME arrays, Gaussian offsets, camera position and near plane
  by s is an exact symmetry of the maths, so anything beyond rounding is a scale-dependent epsilon. That is why
  the head is scaled, not moved: a head translation or a far camera leaves every triangle its size, so the
  frame's guards (compared with edge lengths and cross products, ~L and ~L^2) never see another magnitude.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from hypothesis import example, given, settings
from hypothesis import strategies as st

from gaussiantalker.exporter.export.bundle_export import DEFORM_INPUTS, DEFORM_OUTPUTS
from gaussiantalker.exporter.model.flame import FlameArrays
from gaussiantalker.exporter.model.speaker import Speaker
from gaussiantalker.exporter.verify.bundle_verify import GRAPH_RTOL
from gaussiantalker.runtime import TalkingHead
from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.drive import MAX_DRIVE_MAGNITUDE, FrameDrive, HeadPose
from gaussiantalker.sdk.errors import DriveError
from gaussiantalker.sdk.image import max_abs_error, psnr_db
from gaussiantalker.sdk.numerics import SH_C0

SIZE = (64, 64)
ANGLE_ULPS = 8
MIN_FRAME_PSNR_DB = 60.0
STOP_RULE_BOUND = 0.01  # T at a stopped pixel is < 1e-4 / (1 - 0.99) (runtime/splat/gl.py)
SCALE_RTOL = 1e-4
N_EXPR = 20
PI = math.pi
FACES_PER_GROUP = 10
POINT_COLUMN, SEGMENT_COLUMN = 18, 19  # expression columns that collapse triangles in the geometry speaker
FEW = settings(derandomize=True, max_examples=4, deadline=None)


# -- speakers ---------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def base_speaker(small_speaker) -> Speaker:
    """The session's small demo speaker (2k Gaussians; never modified here)."""
    return small_speaker


@pytest.fixture(scope="module")
def base_head(small_export):
    """The base speaker's session bundle, loaded by the runtime."""
    with TalkingHead(small_export.path, resolution=SIZE) as head:
        yield head


def _disjoint_faces(arrays: FlameArrays, parent: np.ndarray, count: int) -> list[np.ndarray]:
    """Three groups of `count` Gaussian-bearing faces of the head proper that share no vertex with each other."""
    used: set[int] = set()
    chosen = []
    for face in np.unique(parent):
        vertices = set(arrays.faces[face].tolist())
        if max(vertices) < arrays.n_base_vertices and not used & vertices:
            used |= vertices
            chosen.append(face)
        if len(chosen) == 3 * count:
            break
    return [np.array(chosen[i::3]) for i in range(3)]


def _degenerate_arrays(arrays: FlameArrays, shape: np.ndarray, groups: list[np.ndarray]) -> FlameArrays:
    """FLAME arrays where expression 18 = 1 collapses group 0 to points, 19 = 1 group 1 to segments, and
    group 2 has coincident vertices (v1 a copy of v0 in every basis, so they coincide under any drive)."""
    shaped = arrays.v_template.astype(np.float64) + arrays.shapedirs.astype(np.float64) @ shape  # [V, 3]
    exprdirs = arrays.exprdirs.copy()
    exprdirs[:, :, POINT_COLUMN:] = 0.0
    for v0, v1, v2 in arrays.faces[groups[0]]:
        exprdirs[v1, :, POINT_COLUMN] = shaped[v0] - shaped[v1]
        exprdirs[v2, :, POINT_COLUMN] = shaped[v0] - shaped[v2]
    for v0, v1, v2 in arrays.faces[groups[1]]:
        exprdirs[v2, :, SEGMENT_COLUMN] = 0.5 * (shaped[v0] + shaped[v1]) - shaped[v2]
    copied = {key: getattr(arrays, key).copy() for key in ("v_template", "shapedirs", "lbs_weights", "posedirs")}
    for v0, v1, _ in arrays.faces[groups[2]]:
        for key in ("v_template", "shapedirs", "lbs_weights"):
            copied[key][v1] = copied[key][v0]
        exprdirs[v1] = exprdirs[v0]
        copied["posedirs"][:, 3 * v1:3 * v1 + 3] = copied["posedirs"][:, 3 * v0:3 * v0 + 3]
    return replace(arrays, exprdirs=exprdirs.astype(np.float32), **copied).validate()


def _scaled_speaker(base: Speaker, arrays: FlameArrays, scale: float) -> Speaker:
    """`base` with FLAME arrays `arrays`, every length (FLAME positions, Gaussian offsets, camera) times `scale`."""
    scaled = replace(arrays, **{k: (getattr(arrays, k) * np.float32(scale)).astype(np.float32)
                                for k in ("v_template", "shapedirs", "exprdirs", "posedirs")}).validate()
    cam = base.camera
    camera = Camera(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, cam.R, cam.t * scale, cam.near * scale)
    track = base.pose_track.clone()
    track[:, 3:] *= scale
    speaker = Speaker(base.config, scaled, base.shape, base.gaussians.parent, camera, base.background, track)
    speaker.translator.load_state_dict(base.translator.state_dict())
    speaker.latent_pose.load_state_dict(base.latent_pose.state_dict())
    state = base.gaussians.state_dict()
    state["local_position"] = state["local_position"] * scale
    state["w_pos"] = state["w_pos"] * scale
    speaker.gaussians.load_state_dict(state)
    return speaker.eval()


@pytest.fixture(scope="module")
def degenerate_setup(base_speaker):
    """(FLAME arrays with collapsible / coincident triangles, the three face groups, their Gaussians' masks)."""
    parent = base_speaker.gaussians.parent.numpy()
    groups = _disjoint_faces(base_speaker.flame_arrays, parent, FACES_PER_GROUP)
    arrays = _degenerate_arrays(base_speaker.flame_arrays, base_speaker.shape.numpy().astype(np.float64), groups)
    return arrays, groups, [np.isin(parent, g) for g in groups]


@pytest.fixture(scope="module")
def unit_geometry(base_speaker, degenerate_setup) -> Speaker:
    """The degenerate-geometry speaker at scale 1 (torch only): reference of the scaled ones."""
    return _scaled_speaker(base_speaker, degenerate_setup[0], 1.0)


@pytest.fixture(scope="module", params=[1e-3, 1e3], ids=["scale1e-3", "scale1e3"])
def geometry(request, base_speaker, degenerate_setup, small_export, export_rebound, tmp_path_factory):
    """(scale, degenerate-geometry speaker at that scale, its runtime head). Same architecture as the base speaker,
    so its bundle is the base speaker's recorded graphs with this speaker's weights (conftest `export_rebound`)."""
    speaker = _scaled_speaker(base_speaker, degenerate_setup[0], request.param)
    path = export_rebound(speaker, tmp_path_factory.mktemp("geometry") / "geometry.gtb", small_export).path
    with TalkingHead(path, resolution=SIZE) as head:
        yield request.param, speaker, head


# -- comparisons ------------------------------------------------------------------------------------------------


def _torch_deform(speaker: Speaker, inputs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    with torch.no_grad():
        out = speaker.deform(*(torch.from_numpy(inputs[k]) for k in DEFORM_INPUTS))
    return {name: value.numpy() for name, value in zip(DEFORM_OUTPUTS, out, strict=True)}


def _inputs(drive: FrameDrive, center: np.ndarray) -> dict[str, np.ndarray]:
    inputs = drive.graph_inputs()
    inputs["camera_center"] = np.asarray(center, np.float32).reshape(1, 3)
    return inputs


def _max_angle(drive: FrameDrive) -> float:
    return float(np.linalg.norm(drive.flame_pose.astype(np.float64).reshape(5, 3), axis=1).max())


def graph_rtol(drive: FrameDrive) -> float:
    """Graph parity bound for this drive (module docstring: fp32 bound + angle conditioning)."""
    return GRAPH_RTOL + ANGLE_ULPS * 2.0**-24 * _max_angle(drive)


def _relative_errors(reference: dict, test: dict) -> dict[str, float]:
    """max |test - reference| / max |reference| per output."""
    errors = {}
    for name in DEFORM_OUTPUTS:
        ref, out = reference[name].astype(np.float64), test[name].astype(np.float64)
        errors[name] = float(np.abs(out - ref).max() / max(np.abs(ref).max(), 1e-30))
    return errors


def check_graph(speaker: Speaker, head: TalkingHead, drive: FrameDrive, center=None) -> float:
    """Assert torch and ONNX `deform` outputs are finite and agree; return the worst relative error."""
    inputs = _inputs(drive, head.camera.center if center is None else center)
    reference, graph = _torch_deform(speaker, inputs), head.frame_renderer.graphs.run("deform", inputs)
    for name in DEFORM_OUTPUTS:
        assert np.isfinite(reference[name]).all(), f"torch {name} not finite"
        assert np.isfinite(graph[name]).all(), f"onnx {name} not finite"
    errors = _relative_errors(reference, graph)
    bound = graph_rtol(drive)
    assert max(errors.values()) <= bound, (errors, bound)
    return max(errors.values())


def check_frame(speaker: Speaker, head: TalkingHead, drive: FrameDrive, *, torch_gaussians: bool = False
                ) -> tuple[float, float]:
    """Assert the torch and runtime float frames are finite and agree; return (PSNR dB, max abs error).

    torch_gaussians: the runtime splats the torch speaker's Gaussians instead of its own graph's, for drives whose
    deformation is only float32-defined to the angle-conditioning bound (the graph check covers that part).
    """
    reference = speaker.render(drive, head.camera).numpy()
    if torch_gaussians:
        out = _torch_deform(speaker, _inputs(drive, head.camera.center))
        prepared = head.frame_renderer.splatter.prepare(out["means"][0], out["cov3d"][0], out["rgb"][0],
                                                        out["opacity"], head.camera)
        frame = head.frame_renderer.draw(prepared, output="float")
    else:
        frame = head.render(drive, output="float")
    assert np.isfinite(reference).all() and np.isfinite(frame).all()
    psnr = min(psnr_db(reference, frame), 200.0)
    # Frames agree to MIN_FRAME_PSNR_DB, or else within the one documented difference between the two: GL cannot stop
    # a saturated pixel, so the Gaussians the reference skips still add up to 0.01 x the colour range
    # (runtime/splat/gl.py, docs/numerics.md). The opaque head saturates most pixels, so extreme drives that crowd
    # its splats reach that bound (59.96 dB at expression +-1e3), and colours far outside [0, 1] (rotations of 1e4
    # rad drive the latent-pose MLP, and with it the colour offsets, to ~20) widen it.
    if psnr < MIN_FRAME_PSNR_DB:
        if not torch_gaussians:
            out = _torch_deform(speaker, _inputs(drive, head.camera.center))
        spread = float(np.abs(out["rgb"][0] - np.asarray(speaker.background, np.float32)).max())
        assert max_abs_error(reference, frame) <= STOP_RULE_BOUND * max(1.0, spread), (psnr, spread)
    return psnr, max_abs_error(reference, frame)


class Worst:
    """Worst observed graph error and frame PSNR over the examples of one property."""

    def __init__(self) -> None:
        self.err, self.psnr, self.count = 0.0, math.inf, 0

    def add(self, err: float, psnr: float = math.inf) -> None:
        self.err, self.psnr, self.count = max(self.err, err), min(self.psnr, psnr), self.count + 1

    def text(self) -> str:
        return f"finite; torch vs ONNX max rel {self.err:.1e}; frame PSNR >= {self.psnr:.0f} dB ({self.count} drives)"


def check_case(speaker: Speaker, head: TalkingHead, drive: FrameDrive, worst: Worst) -> None:
    """Graph and frame checks of one drive, folded into `worst`."""
    worst.add(check_graph(speaker, head, drive), check_frame(speaker, head, drive)[0])


def _floats(limit: float):
    """Finite floats in [-limit, limit]."""
    return st.floats(-limit, limit, allow_nan=False, allow_infinity=False)


# -- drive ------------------------------------------------------------------------------------------------------


def test_expression_to_ten_sigma(base_speaker, base_head, stability):
    """All expression coefficients anywhere in +-10 sigma at once: blendshape sums far outside training."""
    worst = Worst()

    @FEW
    @given(st.lists(_floats(10.0), min_size=N_EXPR, max_size=N_EXPR))
    @example([10.0] * N_EXPR)
    @example([-10.0] * N_EXPR)
    def run(expression):
        check_case(base_speaker, base_head, FrameDrive.make(N_EXPR, expression), worst)

    run()
    stability.record("drive", "expression coefficients up to +-10 sigma (all 20 at once)", worst.text())


def test_jaw_past_anatomical_range(base_speaker, base_head, stability):
    """Jaw rotations past anatomy both ways (the jaw swings through the skull): posedirs and LBS stay finite."""
    worst = Worst()

    @FEW
    @given(_floats(4 * PI), _floats(PI), _floats(PI))
    @example(PI, 0.0, 0.0)
    @example(-PI, 0.0, 0.0)
    @example(4 * PI, PI, -PI)
    def run(opening, yaw, roll):
        check_case(base_speaker, base_head, FrameDrive.make(N_EXPR, jaw_pose=[opening, yaw, roll]), worst)

    run()
    stability.record("drive", "jaw opened/closed to +-4 pi (negative = through the skull), sideways +-pi", worst.text())


@pytest.mark.parametrize("joint", ["neck", "global"])
def test_neck_and_global_rotation(base_speaker, base_head, stability, joint):
    """Neck / global rotations up to +-pi per component: the whole head turns away, upside down, or back to front."""
    worst = Worst()

    @FEW
    @given(st.lists(_floats(PI), min_size=3, max_size=3))
    @example([PI, 0.0, 0.0])
    @example([0.0, -PI, 0.0])
    def run(rotation):
        drive = (FrameDrive.make(N_EXPR, neck_pose=rotation) if joint == "neck"
                 else FrameDrive.make(N_EXPR, head_pose=HeadPose.make(rotation)))
        check_case(base_speaker, base_head, drive, worst)

    run()
    stability.record("drive", f"{joint} rotation, each component to +-pi", worst.text())


def test_eye_rotation(base_speaker, base_head, stability):
    """Eyeballs turned up to +-pi per component (inside the skull): their triangles stay well-formed."""
    worst = Worst()

    @FEW
    @given(st.lists(_floats(PI), min_size=6, max_size=6))
    @example([PI, 0.0, 0.0, -PI, 0.0, 0.0])
    def run(eyes):
        check_case(base_speaker, base_head, FrameDrive.make(N_EXPR, eye_pose=eyes), worst)

    run()
    stability.record("drive", "eye rotations, each component to +-pi", worst.text())


# Where the head's centre is put, in metres along the camera's viewing axis from the camera centre.
PLACEMENTS = {
    "head 0.3 m in front of the camera (partly inside the near plane)": 0.3,
    "head centre on the near plane (half culled)": 0.2,
    "head centre on the camera centre": 0.0,
    "head 0.5 m behind the camera": -0.5,
}


@pytest.mark.parametrize("case", list(PLACEMENTS))
def test_head_toward_onto_behind_camera(base_speaker, base_head, stability, case):
    """Head moved to the near plane, onto and behind the camera: SH directions finite, culling identical."""
    camera = base_head.camera
    rest = _torch_deform(base_speaker, _inputs(FrameDrive.make(N_EXPR), camera.center))["means"][0].mean(0)
    translation = camera.center + PLACEMENTS[case] * camera.R[2] - rest  # R[2]: viewing axis in world
    drive = FrameDrive.make(N_EXPR, head_pose=HeadPose.make(None, translation))
    err = check_graph(base_speaker, base_head, drive)
    psnr, max_err = check_frame(base_speaker, base_head, drive)
    stability.record("drive", case, f"finite; torch vs ONNX max rel {err:.1e}; frame PSNR {psnr:.0f} dB, "
                                    f"max abs {max_err:.1e}")


def test_gaussian_exactly_at_camera_centre(base_speaker, base_head, stability):
    """A centre on the camera centre has no view direction: its SH colour must stay finite (guarded normalisation).

    Its direction is float rounding (torch: exactly 0; onnxruntime: ~1e-8 m of noise, normalised), so only the
    colour of Gaussians that can reach a pixel (at least `camera.near` from the camera centre) is compared; the
    one at the centre is culled by the near plane on both sides, so its colour never shows.
    """
    drive = FrameDrive.make(N_EXPR)
    means = _torch_deform(base_speaker, _inputs(drive, base_head.camera.center))["means"][0]
    inputs = _inputs(drive, means[0])
    reference, graph = _torch_deform(base_speaker, inputs), base_head.frame_renderer.graphs.run("deform", inputs)
    assert all(np.isfinite(reference[k]).all() and np.isfinite(graph[k]).all() for k in DEFORM_OUTPUTS)
    with torch.no_grad():  # torch: no direction, so only the degree-0 band kappa0' = kappa0 + BS(gamma; W_color)
        gamma = base_speaker.latent_pose(torch.from_numpy(drive.flame_pose[None, 3:]))[0]
        dc = (base_speaker.gaussians.sh[0, 0] + base_speaker.gaussians.w_color[0] @ gamma).numpy()
    np.testing.assert_allclose(reference["rgb"][0, 0], np.maximum(SH_C0 * dc + 0.5, 0.0), atol=1e-6)
    culled_err = float(np.abs(reference["rgb"][0, 0] - graph["rgb"][0, 0]).max())
    visible = np.linalg.norm(means - means[0], axis=1) >= base_head.camera.near
    for output in (reference, graph):
        output["rgb"] = output["rgb"][:, visible]
    errors = _relative_errors(reference, graph)
    assert max(errors.values()) <= GRAPH_RTOL, errors
    stability.record("drive", "camera centre exactly on a Gaussian centre (zero view direction)",
                     f"finite; torch vs ONNX max rel {max(errors.values()):.1e} on the {visible.sum()} Gaussians "
                     f">= near from the camera; the culled one's colour differs by {culled_err:.1e} (its view "
                     f"direction is rounding noise)")


LIMIT_FIELDS = ["expression", "jaw_pose", "neck_pose", "eye_pose", "head rotation", "head translation", "all"]


def _limit_drive(field: str, sign: float) -> FrameDrive:
    """Every value of `field` (or of every field) at +-MAX_DRIVE_MAGNITUDE, alternating sign."""
    def value(name: str, size: int):
        return None if field not in (name, "all") else sign * MAX_DRIVE_MAGNITUDE * (-1.0) ** np.arange(size)
    pose = HeadPose.make(value("head rotation", 3), value("head translation", 3))
    return FrameDrive.make(N_EXPR, value("expression", N_EXPR), value("jaw_pose", 3), value("neck_pose", 3),
                           value("eye_pose", 6), pose)


@pytest.mark.parametrize("field", LIMIT_FIELDS)
def test_drive_at_the_validation_limit(base_speaker, base_head, stability, field):
    """The largest accepted values: nothing overflows; the bound grows with the rotation angle (docstring)."""
    worst = Worst()
    for sign in (1.0, -1.0):
        check_case(base_speaker, base_head, _limit_drive(field, sign), worst)
    bound = graph_rtol(_limit_drive(field, 1.0))
    stability.record("drive", f"{field} at +-{MAX_DRIVE_MAGNITUDE:g} (the validation limit)",
                     worst.text() + f"; bound {bound:.0e}")


def test_rotations_up_to_the_limit(base_speaker, base_head, stability):
    """Rotation vectors anywhere in [-1e4, 1e4]^3: finite; agreement degrades with the angle as the bound says."""
    worst, ratio = Worst(), [0.0]

    @settings(derandomize=True, max_examples=6, deadline=None)
    @given(st.sampled_from(["head rotation", "neck pose", "jaw pose", "eye pose"]),
           st.lists(_floats(MAX_DRIVE_MAGNITUDE), min_size=3, max_size=3))
    @example("jaw pose", [1e4, -7e3, 3e3])
    def run(joint, rotation):
        drive = _make_with(joint, np.tile(rotation, 2) if joint == "eye pose" else np.array(rotation))
        err = check_graph(base_speaker, base_head, drive)
        worst.add(err, check_frame(base_speaker, base_head, drive, torch_gaussians=True)[0])
        ratio[0] = max(ratio[0], err / graph_rtol(drive))

    run()
    stability.record("drive", "global / neck / jaw / eye rotation vectors with components up to +-1e4 rad",
                     worst.text() + f" (frames: runtime splats the torch Gaussians); worst error / bound "
                                    f"{ratio[0]:.2f}")


# -- validation -------------------------------------------------------------------------------------------------

BAD_VALUES = {
    "beyond the limit": (MAX_DRIVE_MAGNITUDE * 1.0001, "exceeds the supported magnitude 10000: {name}\\[1\\] = 10001"),
    "too large for float32": (1e39, "exceeds the supported magnitude 10000: {name}\\[1\\] = 1e\\+39"),
    "NaN": (np.nan, "{name} has non-finite values: {name}\\[1\\] = nan"),
    "+inf": (np.inf, "{name} has non-finite values: {name}\\[1\\] = inf"),
    "-inf": (-np.inf, "{name} has non-finite values: {name}\\[1\\] = -inf"),
}
FIELDS = {"expression": N_EXPR, "jaw pose": 3, "neck pose": 3, "eye pose": 6, "head rotation": 3,
          "head translation": 3}


def _make_with(name: str, values: np.ndarray) -> FrameDrive:
    if name.startswith("head"):
        key = "rotation" if name == "head rotation" else "translation"
        return FrameDrive.make(N_EXPR, head_pose=HeadPose.make(**{key: values}))
    return FrameDrive.make(N_EXPR, **{name.replace(" ", "_"): values})


@pytest.mark.parametrize("bad", list(BAD_VALUES))
def test_bad_drive_values_are_named(stability, bad):
    """Every drive field rejects an unusable value with a DriveError naming field, index, value and limit."""
    value, pattern = BAD_VALUES[bad]
    messages = []
    for name, size in FIELDS.items():
        values = np.zeros(size)
        values[1] = value
        with pytest.raises(DriveError, match=pattern.format(name=name)) as info:
            _make_with(name, values)
        messages.append(str(info.value))
    stability.record("drive", f"drive value {bad} in any field ({len(FIELDS)} fields)",
                     f"DriveError, e.g. '{messages[0]}'")


def test_malformed_drives_are_named(base_head, stability):
    """Non-numeric, complex, mis-shaped or directly built bad drives are DriveErrors too, also via the runtime."""
    cases = [
        (lambda: FrameDrive.make(N_EXPR, jaw_pose="open"), "jaw pose must be an array of real numbers"),
        (lambda: FrameDrive.make(N_EXPR, eye_pose=[1j, 0, 0, 0, 0, 0]), "eye pose must be an array of real numbers"),
        (lambda: FrameDrive.make(N_EXPR, neck_pose=[[0, 0, 0]]), "neck pose must have shape \\(3,\\), got \\(1, 3\\)"),
        (lambda: HeadPose(np.array([0, np.nan, 0]), np.zeros(3)), "head rotation has non-finite values"),
        (lambda: FrameDrive(np.zeros(N_EXPR), np.zeros(15), np.array([0, 0, np.inf])),
         "head translation has non-finite values"),
        (lambda: base_head.render_params(head_translation=[0, 0, -2e4]), "head translation exceeds the supported"),
    ]
    for build, pattern in cases:
        with pytest.raises(DriveError, match=pattern):
            build()
    stability.record("drive", "non-numeric, complex, mis-shaped drive; NaN in a directly built HeadPose/FrameDrive",
                     f"DriveError naming the field ({len(cases)} cases, incl. through TalkingHead.render_params)")


# -- geometry ---------------------------------------------------------------------------------------------------


def _frame_columns(speaker: Speaker, expression: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Column lengths |n0|, |n1|, |n2| [G, 3] and scale S [G] of the triangle frames under the masked Gaussians."""
    from gaussiantalker.exporter.model.gaussians import triangle_frame

    with torch.no_grad():
        vertices = speaker.vertices(torch.from_numpy(expression[None]), torch.zeros(1, 15), torch.zeros(1, 3))[0]
        corners = vertices[speaker.gaussians.vertex_ids[torch.from_numpy(mask)]]  # [G, 3, 3]
        rotation, scale = triangle_frame(corners[:, 0], corners[:, 1], corners[:, 2],
                                         speaker.gaussians.rest_scale[torch.from_numpy(mask)])
    return torch.linalg.vector_norm(rotation, dim=-2).numpy(), scale.numpy()


COLLAPSES = {"point": POINT_COLUMN, "segment": SEGMENT_COLUMN}


@pytest.mark.parametrize("collapse", list(COLLAPSES))
def test_triangles_collapsed_by_drive(geometry, degenerate_setup, stability, collapse):
    """Expression drives triangles through a point / a segment and beyond; the frame fades there, on both sides."""
    scale, speaker, head = geometry
    group = 0 if collapse == "point" else 1
    at_collapse = np.zeros(N_EXPR, np.float32)
    at_collapse[COLLAPSES[collapse]] = 1.0
    columns, size = _frame_columns(speaker, at_collapse, degenerate_setup[2][group])
    rest = speaker.gaussians.rest_scale.numpy()[degenerate_setup[2][group]]
    if collapse == "point":  # really collapsed: the triangles are points (to rounding) and have no frame
        assert (size <= 1e-5 * rest).all() and (columns <= 1e-3).all()
    else:  # segments: n0 along the segment stays, the normal (n1) and n2 fade
        assert (size >= 0.5 * rest).all() and (columns[:, 0] > 0.99).all() and (columns[:, 1:] <= 1e-2).all()
    worst = Worst()

    @settings(derandomize=True, max_examples=4, deadline=None)
    @given(st.one_of(st.just(1.0), st.floats(1 - 1e-3, 1 + 1e-3), st.floats(-3.0, 3.0)), _floats(0.5))
    @example(1.0, 0.0)
    @example(1.0 + 1e-6, 0.3)
    def run(coefficient, jaw):
        expression = np.zeros(N_EXPR)
        expression[COLLAPSES[collapse]] = coefficient
        check_case(speaker, head, FrameDrive.make(N_EXPR, expression, [jaw, 0, 0]), worst)

    run()
    stability.record("geometry", f"triangles driven through a {collapse} (coefficient 1 +- 1e-3, +-3), "
                                 f"head scale {scale:g}", worst.text())


def test_coincident_vertices(geometry, degenerate_setup, stability):
    """Faces whose v0 and v1 coincide in every basis: n0 = 0 exactly, so their Gaussians have zero covariance."""
    scale, speaker, head = geometry
    mask = degenerate_setup[2][2]
    worst = Worst()
    rng = np.random.default_rng(5)
    for drive in (FrameDrive.make(N_EXPR), FrameDrive.make(N_EXPR, rng.normal(0, 3, N_EXPR), [0.3, 0, 0])):
        cov = head.frame_renderer.graphs.run("deform", _inputs(drive, head.camera.center))["cov3d"][0]
        assert (cov[mask] == 0).all()  # a zero frame, not a NaN and not a noise-driven unit one
        check_case(speaker, head, drive, worst)
    stability.record("geometry", f"coincident vertices (v0 = v1 in every basis), head scale {scale:g}",
                     worst.text() + "; their Gaussians get an exactly zero frame on both sides")


def test_scaled_head_graph_and_frame(geometry, stability):
    """A head in other units (1e-3: millimetre-sized; 1e3: kilometre-sized) through the exported graph."""
    scale, speaker, head = geometry
    worst = Worst()
    rng = np.random.default_rng(2)
    for drive in (FrameDrive.make(N_EXPR), FrameDrive.make(N_EXPR, rng.normal(0, 2, N_EXPR), [0.4, 0.1, 0],
                                                           head_pose=HeadPose.make([0.2, 0.5, 0.1]))):
        check_case(speaker, head, drive, worst)
    stability.record("geometry", f"whole head scaled by {scale:g} (FLAME arrays, offsets, camera)", worst.text())


def test_scale_invariance(base_speaker, degenerate_setup, unit_geometry, stability):
    """Scaling every length by s (1e-4 .. 1e4) scales means by s and cov3d by s^2 and leaves the frame alone."""
    camera = unit_geometry.camera.resized(*SIZE)
    worst_err, worst_psnr = [0.0], [math.inf]

    @settings(derandomize=True, max_examples=5, deadline=None)
    @given(st.floats(-4.0, 4.0), st.lists(_floats(3.0), min_size=N_EXPR, max_size=N_EXPR), _floats(0.5))
    @example(-4.0, [0.0] * N_EXPR, 0.0)
    @example(-3.0, [3.0] * N_EXPR, 0.5)
    @example(4.0, [-3.0] * N_EXPR, -0.5)
    def run(log_scale, expression, jaw):
        scale = 10.0**log_scale
        speaker = _scaled_speaker(base_speaker, degenerate_setup[0], scale)
        drive = FrameDrive.make(N_EXPR, expression, [jaw, 0, 0])
        reference = _torch_deform(unit_geometry, _inputs(drive, unit_geometry.camera.center))
        scaled = _torch_deform(speaker, _inputs(drive, speaker.camera.center))
        for name, power in (("means", 1), ("cov3d", 2)):
            scaled[name] = scaled[name] / scale**power
        for name in DEFORM_OUTPUTS:
            assert np.isfinite(scaled[name]).all(), name
        errors = _relative_errors(reference, scaled)
        assert max(errors.values()) <= SCALE_RTOL, (scale, errors)
        frame = speaker.render(drive, speaker.camera.resized(*SIZE)).numpy()
        psnr = min(psnr_db(unit_geometry.render(drive, camera).numpy(), frame), 200.0)
        assert np.isfinite(frame).all() and psnr >= MIN_FRAME_PSNR_DB, (scale, psnr)
        worst_err[0], worst_psnr[0] = max(worst_err[0], max(errors.values())), min(worst_psnr[0], psnr)

    run()
    stability.record("geometry", "head scale 1e-4 .. 1e4, torch (means / s, cov3d / s^2 vs scale 1)",
                     f"finite; max rel deviation {worst_err[0]:.1e}; frames vs scale 1: PSNR >= {worst_psnr[0]:.0f} dB")
