"""`gt-bench avatar` end to end on a tiny synthetic LAM avatar (tests/lam_avatars.py) beside a tiny demo speaker:
both reports are written and hold a finite number for every measure of every preset."""

from __future__ import annotations

import json
import math

import pytest
from lam_avatars import write_avatar_zip
from typer.testing import CliRunner

from tools.bench.app import app

pytestmark = pytest.mark.slow  # three torch.onnx exports (three presets) and a verify: over 20 s
# quality (the reference), compact (a size ratio above 1) and fast (played in the FPS rounds); `--presets` picks
# them, as it does for users; the other presets take the same code path.
PRESET_SUBSET = ("quality", "compact", "fast")


def test_bench_avatar_writes_every_measure(tmp_path, small_export):
    """Beside an exported speaker (`--demo-bundle`; the GaussianAvatars bench's test exports one from
    `--demo-checkpoint`)."""
    avatar = write_avatar_zip(tmp_path / "avatar.zip")
    out = tmp_path / "bench"
    result = CliRunner().invoke(app, ["avatar", str(avatar), "--demo-bundle", str(small_export.path),
                                      "--frames", "4", "--fps-seconds", "0.4", "--rounds", "1", "--presets",
                                      ",".join(PRESET_SUBSET), "--verify-frames", "2", "--variant",
                                      "fast full=fast:render_scale=1,render_target=float32,alpha_min=1/255,"
                                      "max_draw_pixels=0", "--out", str(out)])
    assert result.exit_code == 0, result.output
    report = json.loads((out / "avatar.json").read_text())
    markdown = (out / "avatar.md").read_text()
    assert set(report["presets"]) == set(PRESET_SUBSET)
    assert "the avatar's own motion track" in report["quality"]["motion"]
    assert len(report["quality"]["frames"]) == 4
    numbers = [report["import_s"], report["verify"]["verify_s"]]
    assert report["verify"]["min_psnr_db"] >= 50.0  # the fp32 tier's bound; inf where the frames equal torch's
    for name, preset in report["presets"].items():
        numbers += [preset["export_s"], *preset["export_s_rounds"], preset["bundle_mb"], preset["smaller_than_fp32"]]
        assert len(preset["export_s_rounds"]) == 1
        if name != "quality":
            numbers += [preset["head_psnr_median_db"], preset["head_psnr_min_db"]]
            assert f"| {name} |" in markdown
    assert report["presets"]["quality"]["smaller_than_fp32"] == 1.0
    assert report["presets"]["compact"]["smaller_than_fp32"] > 1.0
    variant = report["variants"]["fast full"]  # fast's bundle at full scale: its stored render settings overridden
    assert variant["preset"] == "fast" and variant["runtime"]["render_scale"] == 1.0
    assert variant["runtime"]["max_draw_pixels"] is None and "| fast full | fast | scale 1, float32" in markdown
    numbers += [variant["head_psnr_median_db"], variant["head_psnr_min_db"]]
    cases = report["fps"]["cases"]
    assert set(cases) == {f"avatar {name}" for name in PRESET_SUBSET} | {"avatar fast full", "demo speaker fp32"}
    for case in cases.values():
        numbers += [case["frame_ms"], case["fps"], *case["fps_rounds"]]
        assert len(case["frame_ms_rounds"]) == 1
    numbers += list(report["fps"]["fps_vs_demo"].values())
    assert report["fps"]["demo_gaussians"] == small_export.speaker.gaussians.count
    assert all(math.isfinite(n) and n > 0 for n in numbers), numbers
    assert report["command"].startswith("gt-bench") and "## Frames per second" in markdown


def test_the_demo_speaker_is_given_once(tmp_path, small_export):
    demo = tmp_path / "demo.ckpt"
    demo.write_bytes(b"")
    result = CliRunner().invoke(app, ["avatar", str(write_avatar_zip(tmp_path / "avatar.zip")), "--demo-checkpoint",
                                      str(demo), "--demo-bundle", str(small_export.path)])
    assert result.exit_code == 2 and "give the demo speaker once" in result.output
