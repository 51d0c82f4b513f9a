"""`gt-bench sweep`: the cases cover every knob, the quality metrics measure what they claim, and a tiny sweep runs
end to end (speed figures are not judged here: they belong to the benchmark's own report)."""

from __future__ import annotations

import math
from dataclasses import fields

import numpy as np
import pytest
from typer.testing import CliRunner

from gaussiantalker.exporter.export.presets import CODEC_GROUPS, PRESETS, ExportSettings
from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.render_settings import EXPERIMENTAL_FIELDS, RenderSettings
from tools.bench.app import app
from tools.bench.clip_crf import CLIP_CRFS, clip_settings
from tools.bench.composite_cost import F_CODECS, f_codec_settings
from tools.bench.quality import mouth_box, region_scores, ssim_map
from tools.bench.report import format_report, goal_rows, pareto_front
from tools.bench.sweep import REFERENCE, select_cases, sweep_cases, sweep_speaker


def test_every_knob_and_preset_is_swept():
    cases = sweep_cases()
    names = [c.name for c in cases]
    assert len(names) == len(set(names)) and names[0] == REFERENCE
    assert {c.preset for c in cases if c.preset} == set(PRESETS)
    swept_export = {f.name for c in cases if not c.preset for f in fields(ExportSettings)
                    if getattr(c.export, f.name) != getattr(ExportSettings(), f.name)}
    # F's codec shows only in composited frames: the compositing bench sweeps it, the sweep (bare head) does not.
    swept_by_composite = {f.name for s in f_codec_settings() for f in fields(ExportSettings)
                          if getattr(s, f.name) != getattr(ExportSettings(), f.name)}
    assert swept_by_composite == {"inpaint"} and "inpaint" not in swept_export
    assert len({s.inpaint for s in f_codec_settings()}) == len(F_CODECS) >= 3
    # The reference clip's setting likewise: `gt-bench clip-crf` sweeps it.
    swept_by_clip = {f.name for s in clip_settings() for f in fields(ExportSettings)
                     if getattr(s, f.name) != getattr(ExportSettings(), f.name)}
    assert swept_by_clip == {"reference"} and "reference" not in swept_export
    assert len({s.reference for s in clip_settings()}) == len(CLIP_CRFS) + 1 >= 4
    assert swept_export | swept_by_composite | swept_by_clip == {f.name for f in fields(ExportSettings)}
    assert set(CODEC_GROUPS) <= swept_export | swept_by_composite
    swept_runtime = {key for c in cases for key in c.runtime}
    # TalkingHead takes RenderSettings.graph_threads as its `threads` argument; experimental fields are left out.
    assert swept_runtime == {"threads" if f.name == "graph_threads" else f.name for f in fields(RenderSettings)
                             if f.name not in EXPERIMENTAL_FIELDS}
    for case in cases:  # one knob at a time: a knob case changes exactly one setting
        if not case.preset:
            changed = [f.name for f in fields(ExportSettings)
                       if getattr(case.export, f.name) != getattr(ExportSettings(), f.name)]
            if "refit_steps" in changed:  # a refit fits what a budget keeps, so its case has one
                changed.remove("gaussian_budget")
            assert len(changed) + len(case.runtime) == 1, case


def test_case_selection():
    chosen = select_cases(sweep_cases(), "preset, sort")
    assert [c.name for c in chosen if c.preset] == list(PRESETS)
    assert {c.group for c in chosen if not c.preset} == {"sort interval", "sort key bits"}
    with pytest.raises(ValueError, match="no sweep case matches 'zoom'"):
        select_cases(sweep_cases(), "zoom")


def test_unknown_cases_are_a_cli_error():
    result = CliRunner().invoke(app, ["sweep", "--cases", "zoom"])
    assert result.exit_code == 2 and "no sweep case matches 'zoom'" in result.output


@pytest.mark.parametrize("renderers", ["vulkan", "", "gl,metal"])
def test_unknown_renderers_are_a_cli_error(renderers):
    result = CliRunner().invoke(app, ["sweep", "--renderers", renderers])
    assert result.exit_code == 2 and "renderers must be gl, cpu or both" in result.output


def test_steady_frame_time_is_the_clip_rate_of_a_bursty_loop():
    """A loop that hands over frames two at a time (gaps 0 and 2T) runs at T a frame: the mean gap after the
    warm-up, not the median (which would be 0 or 2T)."""
    from tools.bench.worker import steady_frame_ms

    walls = [0.5, 0.4] + [0.0, 0.02] * 20
    assert steady_frame_ms(walls, warmup=2) == pytest.approx(10.0)
    assert steady_frame_ms([0.01] * 3, warmup=5) == pytest.approx(10.0)  # a clip shorter than the warm-up


def test_ssim_of_constant_frames_is_the_luminance_term():
    """Flat frames have no variance, so SSIM = (2ab + C1) / (a^2 + b^2 + C1) exactly; equal frames give 1."""
    a, b = 100, 140
    x, y = np.full((20, 24, 3), a, np.uint8), np.full((20, 24, 3), b, np.uint8)
    c1 = 0.01**2
    expected = (2 * a * b / 255**2 + c1) / ((a**2 + b**2) / 255**2 + c1)
    np.testing.assert_allclose(ssim_map(x, y), expected, rtol=1e-5)
    noisy = np.random.default_rng(0).integers(0, 256, (20, 24, 3), dtype=np.uint8)
    np.testing.assert_allclose(ssim_map(noisy, noisy), 1.0, rtol=1e-5)
    assert ssim_map(noisy, 255 - noisy).mean() < 0


def test_region_scores_only_see_their_region():
    rng = np.random.default_rng(1)
    reference = rng.integers(0, 256, (40, 50, 3), dtype=np.uint8)
    test = reference.copy()
    test[:, :10] = 0  # damage outside the region
    region = np.zeros((40, 50), bool)
    region[10:30, 25:45] = True
    (psnr, ssim), (empty_psnr, empty_ssim) = region_scores(reference, test, [region, np.zeros_like(region)])
    assert math.isinf(psnr) and ssim == pytest.approx(1.0)
    assert math.isinf(empty_psnr) and empty_ssim == 1.0
    test[20, 30] = reference[20, 30] ^ 0xFF
    (psnr, ssim), = region_scores(reference, test, [region])
    assert 20 < psnr < 60 and ssim < 1.0


def test_mouth_box_surrounds_the_projected_points():
    camera = Camera(100, 80, 50.0, 50.0, 50.0, 40.0, np.eye(3), np.zeros(3), 0.01)
    points = np.array([[0.0, 0.0, 1.0], [0.2, 0.1, 1.0]])  # pixels (50, 40) and (60, 45)
    row0, row1, col0, col1 = mouth_box(points, camera)
    pad = 3  # MOUTH_BOX_PAD * 100 px
    assert (row0, row1, col0, col1) == (40 - pad, 45 + pad, 50 - pad, 60 + pad)
    assert mouth_box(np.array([[0.0, 0.0, -1.0]]), camera) == (0, 0, 0, 0)  # behind the camera


def test_pareto_front():
    points = {"a": (1.0, 30.0), "b": (2.0, 40.0), "c": (2.0, 35.0), "d": (3.0, 40.0), "e": (0.5, 20.0)}
    assert pareto_front(points) == {"a", "b", "e"}


def test_tiny_sweep_end_to_end(small_export, replay_onnx_exports, tmp_path):
    """Two bundles (fp32, gaussians q8: the same graphs, replayed instead of exported again) and two runtime
    knobs, 64x64, two rounds: every column is filled, the reference is identical to itself, a lossy knob is
    measured as lossy, and the report and plot are written."""
    replay_onnx_exports(small_export.protos * 2)
    cases = select_cases(sweep_cases(), "gaussians q8,framebuffer uint8,sort keys")
    sweep = sweep_speaker("small speaker", small_export.speaker, cases, sizes=[64], seconds=0.5, rounds=2,
                          warmup=2, progress=False)
    assert list(sweep.cases) == [c.name for c in cases]
    reference, quantised = sweep.cases[REFERENCE], sweep.cases["gaussians q8"]
    uint8 = sweep.cases["framebuffer uint8"]
    assert quantised["bundle_bytes"] < reference["bundle_bytes"] == uint8["bundle_bytes"]
    ref_quality = reference["sizes"]["64"]["quality"]
    assert math.isinf(ref_quality["head_psnr_db"]) and ref_quality["head_ssim"] == pytest.approx(1.0)
    assert ref_quality["flame_max_abs"] == 0.0
    for name in ("gaussians q8", "framebuffer uint8"):
        quality = sweep.cases[name]["sizes"]["64"]["quality"]
        assert 15.0 < quality["head_psnr_db"] < 80.0 and quality["head_ssim"] < 1.0, name
    for case in sweep.cases.values():
        at = case["sizes"]["64"]
        assert at["rounds"] == 2 and len(at["fps_vs_reference_rounds"]) == 2
        assert at["frame_ms"] > 0 and at["fps"] > 0 and at["load_s"] > 0 and case["peak_rss_mb"] > 50
        assert set(at["stages_ms"]) == {"translator", "deformation", "sort", "upload", "draw", "readback"}
    assert reference["sizes"]["64"]["fps_vs_reference"] == 1.0
    report = format_report([sweep], {"cores": 2}, "gt-bench sweep")
    for name in sweep.cases:
        assert f"| {name} |" in report or f"| **{name}** |" in report
    assert goal_rows(sweep) == []  # no preset but the reference was swept
    from tools.bench.report import plot_sweep  # matplotlib: in the dev extra, so always tested

    png = plot_sweep([sweep], tmp_path / "sweep.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_sweep_measures_each_splatter_against_its_own_reference(small_export, replay_onnx_exports):
    """`--renderers gl,cpu`: every case drawn by both splatters in the same rounds, one sweep per splatter named by
    it, each case's ratio and quality taken against `quality` drawn by the same splatter."""
    from tools.bench.sweep import sweep_speaker_renderers

    replay_onnx_exports(small_export.protos)
    cases = select_cases(sweep_cases(), "sort keys")
    sweeps = sweep_speaker_renderers("small speaker", small_export.speaker, cases, sizes=[64], seconds=0.5,
                                     rounds=1, renderers=("gl", "cpu"), warmup=2, progress=False)
    assert [s.speaker for s in sweeps] == ["small speaker, OpenGL splatter", "small speaker, CPU splatter"]
    for sweep, renderer in zip(sweeps, ("gl", "cpu"), strict=True):
        reference, knob = sweep.cases[REFERENCE], sweep.cases["sort keys 16-bit"]
        assert reference["renderer"] == knob["renderer"] == renderer
        assert math.isinf(reference["sizes"]["64"]["quality"]["head_psnr_db"])  # against its own splatter's frames
        assert reference["sizes"]["64"]["fps_vs_reference"] == 1.0
        assert 20.0 < knob["sizes"]["64"]["quality"]["head_psnr_db"] <= math.inf
    report = format_report(sweeps, {"cores": 2}, "gt-bench sweep --renderers gl,cpu")
    assert "small speaker, OpenGL splatter" in report and "small speaker, CPU splatter" in report


def _case(preset: str | None, bundle_bytes: int, whole_bytes: int | None, fps_ratio: float, psnr: float) -> dict:
    """One swept case as `sweep_speaker_renderers` records it, at 512² only."""
    quality = {"head_psnr_db": psnr, "head_ssim": 0.99, "mouth_psnr_db": psnr, "mouth_ssim": 0.99,
               "flame_max_abs": 0.0}
    at = {"load_s": 0.1, "stages_ms": dict.fromkeys(("translator", "deformation", "sort", "upload", "draw",
                                                     "readback"), 1.0),
          "fps": 100.0 * fps_ratio, "fps_vs_reference": fps_ratio, "quality": quality}
    return {"preset": preset, "bundle_bytes": bundle_bytes, "whole_bytes": whole_bytes, "gaussians": 1000,
            "peak_rss_mb": 100.0, "sizes": {"512": at}}


def test_size_goals_are_on_the_whole_file_where_the_sweep_weighed_it():
    """With the presets' whole files weighed (a speaker with a reference clip), the report shows them beside the
    bare head's bundle and the size goals judge them; without, the bare head's bundle as before."""
    from tools.bench.sweep import SpeakerSweep

    def sweep(whole: bool) -> SpeakerSweep:
        result = SpeakerSweep("demo", 1000)
        result.cases = {REFERENCE: _case(REFERENCE, 14_000_000, 18_000_000 if whole else None, 1.0, math.inf),
                        "balanced": _case("balanced", 3_000_000, 3_300_000 if whole else None, 1.0, 48.0)}
        return result

    weighed, bare = sweep(True), sweep(False)
    rows = {row["goal"]: row for row in goal_rows(weighed) if row["preset"] == "balanced"}
    assert rows["smaller"]["whole_file"] and rows["smaller"]["measured"] == pytest.approx(18 / 3.3)
    assert rows["smaller"]["met"]
    report = format_report([weighed], {"cores": 2}, "gt-bench sweep")
    assert "whole file MB (× smaller)" in report and "| 3.30 (5.5) |" in report
    assert "whole file × smaller | ≥ 5 | 5.45 | met" in report
    rows = {row["goal"]: row for row in goal_rows(bare) if row["preset"] == "balanced"}
    assert not rows["smaller"]["whole_file"] and rows["smaller"]["measured"] == pytest.approx(14 / 3.0)
    assert not rows["smaller"]["met"]
    assert "whole file" not in format_report([bare], {"cores": 2}, "gt-bench sweep")
