"""`gt-bench web-presets` end to end (docs/web.md, "Download size and time to the first frame"): a tiny demo speaker
and a tiny synthetic LAM avatar (whose morph basis is mostly zeros) exported with one preset each, loaded and
drawn in headless Chromium; the report holds each bundle's real size, its sparse bytes, and times that add up.
Fails (not skips) without chromium or the web player's npm install where CI is set (tests/ci_tools.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from ci_tools import BROWSER_INSTALL, need, need_chromium
from lam_avatars import write_avatar_zip
from typer.testing import CliRunner

from gaussiantalker.exporter.demo.demo_speaker import make_demo_speaker
from gaussiantalker.exporter.export.checkpoint import save_checkpoint
from gaussiantalker.exporter.imports.sources.lam import import_lam
from tools.bench.app import app

pytestmark = pytest.mark.slow  # two exports and two Chromium pages: about 30 s


def test_bench_web_presets_reports_sizes_and_time_to_first_frame(tmp_path):
    from tools.browser.web_harness import check_web_player

    need_chromium()
    need(check_web_player(), BROWSER_INSTALL)
    demo, _ = make_demo_speaker(n_gaussians=300, seed=3, train_seconds=0, progress=False)
    save_checkpoint(demo, tmp_path / "demo.ckpt")
    avatar = import_lam(write_avatar_zip(tmp_path / "avatar.zip"), progress=False)
    morphs = avatar.rig.morphs.numpy()
    regional = np.where(np.abs(morphs) >= np.quantile(np.abs(morphs), 0.8), morphs, 0.0)  # 80% zeros, as LAM's
    avatar.rig.morphs.copy_(avatar.rig.morphs.new_tensor(regional))
    save_checkpoint(avatar, tmp_path / "avatar.ckpt")
    out = tmp_path / "bench"
    result = CliRunner().invoke(app, ["web-presets", f"demo={tmp_path / 'demo.ckpt'}:audio=samples/demo_speech.wav",
                                      f"lam={tmp_path / 'avatar.ckpt'}", "--presets", "balanced", "--rounds", "1",
                                      "--out", str(out)])
    assert result.exit_code == 0, result.output
    report = json.loads((out / "web-presets.json").read_text())
    assert "| demo | balanced |" in (out / "web-presets.md").read_text()
    rows = {row["speaker"]: row for row in report["rows"]}
    assert set(rows) == {"demo", "lam"}
    for row in rows.values():
        assert row["bytes"] > sum(row["groups"].get(g, 0) for g in ("graphs", "deform")) > 0
        assert all(row[key] > 0 for key in ("load", "drive", "first_frame"))
        assert row["total"] == pytest.approx(row["load"] + row["drive"] + row["first_frame"], rel=1e-6)
        assert row["download_seconds"]["10"] == pytest.approx(row["bytes"] * 8 / 10e6)
    assert "sparse" not in rows["demo"]["groups"]  # FLAME buffers stay dense
    assert 0 < rows["lam"]["groups"]["sparse"] <= rows["lam"]["groups"]["deform"]  # the morph basis, stored sparse
