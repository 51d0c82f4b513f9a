"""The stability cases of the fp32 path (test_stability_drive.py, test_stability_audio.py) on every reduced bundle.

Each reduced bundle of the small speaker (`reduced_export`: the presets, and the fp16 / int8 translator graphs) is
driven through the extremes those tests use: expression coefficients at +-10 sigma, jaw, neck, global and eye
rotations past anatomy, rotations at the drive limit, the head onto and behind the camera; and audio that is
silent, full-scale clipped noise, or speech clipped by +32 dB. Every graph output and pixel must be finite, and
the frame must still show the head the fp32 bundle shows: head-region PSNR against the fp32 bundle's frame of
the same drive of at least FLOOR_DB where the fp32 frame has a head to compare (the bundles measured 19-54 dB on
this speaker at these extremes, as low as on ordinary speech for compact and fast; a blown-up Gaussian covering the
frame gives < 10 dB), and the jaw must follow the same audio as the fp32 bundle's. Reduced bundles are not held to
the fp32 path's parity with torch: each one's own bound is checked by test_presets.py on ordinary speech.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from gaussiantalker.exporter.export.presets import PRESETS
from gaussiantalker.exporter.export.speech import synth_speech
from gaussiantalker.runtime import TalkingHead
from gaussiantalker.sdk.drive import MAX_DRIVE_MAGNITUDE, FrameDrive, HeadPose
from gaussiantalker.sdk.image import psnr_db

# Rotation vectors of length ~1.7e4 rad: float32 keeps their angle only to ~theta * 2^-23 ~ 2e-3 rad, so any
# change of weights turns the head by a different amount (test_stability_drive.py); only finiteness is checked.
CHAOTIC = {"rotations at the drive limit"}
# A Gaussian budget keeps the largest contributors over its pose sweep (+-0.3 rad): on the opaque demo head the back
# of the head contributes nothing there and is pruned first, so the head turned around shows the holes; only
# finiteness is checked there (verify likewise reports, not judges, budget bundles from novel views).
SEEN_FROM_BEHIND = {"global -pi"}
BUDGET_PRESETS = {name for name, preset in PRESETS.items() if preset.export.gaussian_budget is not None}
# conftest `reduced_export` makes each
REDUCED = ["balanced", "compact", "fast", "mobile", "translator-fp16", "translator-int8"]
SIZE = (64, 64)
# Jaw opening (rad) against the fp32 bundle's on the same extreme audio: measured at most 3.7e-3 (compact's 4-bit
# translator), 8e-4 (int8 graph), 1.7e-4 (quantised buffers, fp16 graph); the jaw's range in speech is ~0.3.
JAW_TOLERANCE = 0.05
FLOOR_DB = 12.0
PI = math.pi
SR = 16_000
JAW = 6  # index of the jaw's x rotation in FrameDrive.flame_pose


def _drives(n_expr: int, head: TalkingHead) -> dict[str, FrameDrive]:
    """The drive extremes of test_stability_drive.py, one representative each."""
    camera = head.camera
    rest = head.frame_renderer.deform(FrameDrive.make(n_expr))["means"].mean(0)
    behind = camera.center - 0.5 * camera.R[2] - rest  # head centre 0.5 m behind the camera
    onto = camera.center - rest
    return {
        "expression +10 sigma": FrameDrive.make(n_expr, np.full(n_expr, 10.0)),
        "expression -10 sigma": FrameDrive.make(n_expr, np.full(n_expr, -10.0)),
        "jaw 4 pi, sideways pi": FrameDrive.make(n_expr, jaw_pose=[4 * PI, PI, -PI]),
        "jaw -pi (through the skull)": FrameDrive.make(n_expr, jaw_pose=[-PI, 0, 0]),
        "neck pi": FrameDrive.make(n_expr, neck_pose=[PI, 0, 0]),
        "global -pi": FrameDrive.make(n_expr, head_pose=HeadPose.make([0, -PI, 0])),
        "eyes pi": FrameDrive.make(n_expr, eye_pose=[PI, 0, 0, -PI, 0, 0]),
        "rotations at the drive limit": FrameDrive.make(n_expr, jaw_pose=[MAX_DRIVE_MAGNITUDE] * 3,
                                                        neck_pose=[-MAX_DRIVE_MAGNITUDE] * 3),
        "head centre on the camera centre": FrameDrive.make(n_expr, head_pose=HeadPose.make(None, onto)),
        "head 0.5 m behind the camera": FrameDrive.make(n_expr, head_pose=HeadPose.make(None, behind)),
    }


def _audio() -> dict[str, np.ndarray]:
    speech = synth_speech(1.0, seed=21)
    rng = np.random.default_rng(12)
    return {
        "silence": np.zeros(SR, np.float32),
        "full-scale clipped noise": np.sign(rng.standard_normal(SR)).astype(np.float32),
        "speech clipped by +32 dB": np.clip(40.0 * speech, -1, 1).astype(np.float32),
    }


@pytest.fixture(scope="module")
def fp32_head(small_export):
    with TalkingHead(small_export.path, resolution=SIZE) as head:
        yield head


@pytest.mark.parametrize("name", REDUCED)
def test_reduced_bundle_stays_finite_at_the_extremes(name, reduced_export, fp32_head, stability):
    n_expr = fp32_head.driver.config.n_expr
    drives = _drives(n_expr, fp32_head)
    worst, checked, jaw_diff = math.inf, 0, 0.0
    with TalkingHead(reduced_export(name), resolution=SIZE) as head:
        for case, drive in drives.items():
            outputs = head.frame_renderer.deform(drive)
            assert all(np.isfinite(v).all() for v in outputs.values()), (name, case)
            frame = head.render(drive, output="float")
            assert np.isfinite(frame).all(), (name, case)
            reference, alpha = fp32_head.render(drive), fp32_head.render(drive, output="rgba")[..., 3] >= 1
            if alpha.sum() >= 20:  # a head to compare (not culled or off-screen in the fp32 frame)
                psnr = psnr_db(reference[alpha], head.render(drive)[alpha])
                if case in CHAOTIC or (name in BUDGET_PRESETS and case in SEEN_FROM_BEHIND):
                    continue
                assert psnr >= FLOOR_DB, (name, case, psnr)
                worst, checked = min(worst, psnr), checked + 1
        for case, audio in _audio().items():
            drives_of_clip = list(head.drives(audio, SR))
            assert len(drives_of_clip) == 25, (name, case)
            assert all(np.isfinite(d.expression).all() and np.isfinite(d.flame_pose).all()
                       for d in drives_of_clip), (name, case)
            widest = max(drives_of_clip, key=lambda d: abs(float(d.flame_pose[JAW])))
            assert np.isfinite(head.render(widest, output="float")).all(), (name, case)
            jaw = np.array([d.flame_pose[JAW] for d in drives_of_clip])
            fp32_jaw = np.array([d.flame_pose[JAW] for d in fp32_head.drives(audio, SR)])
            jaw_diff = max(jaw_diff, float(np.abs(jaw - fp32_jaw).max()))
            if case == "silence":
                assert np.abs(jaw).max() < 1e-6  # the neutral face
        assert jaw_diff < JAW_TOLERANCE, (name, jaw_diff)
    stability.record("reduced bundles", f"{name} bundle: {len(drives)} drive extremes, {len(_audio())} audio extremes",
                     f"finite; head PSNR vs the fp32 bundle >= {worst:.0f} dB over {checked} framed drives; "
                     f"jaw vs the fp32 bundle's on the same audio max {jaw_diff:.1e} rad")
