"""`gt-bench codings` (tools/bench/codings.py): its codebook and spatial-order probes and rewritten bundles, then the
command end to end on a tiny synthetic LAM avatar (tests/lam_avatars.py) at a small size."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from lam_avatars import AvatarSpec, write_avatar_zip
from typer.testing import CliRunner

import tools.bench.codings as codings
from tools.bench.app import app


def test_codebook_counts_float16_centres_and_packed_indices():
    values = np.random.default_rng(2).standard_normal((3, 1000)).astype(np.float32)
    decoded, nbytes, payload = codings.codebook(values, 16)
    assert decoded.shape == values.shape and len(np.unique(decoded, axis=1).T) <= 16
    assert nbytes == len(payload) == 16 * 3 * 2 + math.ceil(1000 * 4 / 8)


def test_a_spatial_order_is_undone_after_quantising():
    """Quantised in another order, the values come back in theirs, each within half its chunk's step."""
    rng = np.random.default_rng(4)
    values = rng.standard_normal((3, 2000)).astype(np.float32)
    order = rng.permutation(2000)
    decoded, nbytes, _ = codings.quantised(values, "q8", None, order)
    assert np.abs(decoded - values).max() <= (values.max() - values.min()) / 255 / 2 + 1e-6
    same, _, _ = codings.quantised(values, "q8", None, np.arange(2000))
    plain, plain_bytes, _ = codings.quantised(values, "q8", None, None)
    assert np.array_equal(same, plain) and nbytes == plain_bytes


@pytest.fixture(scope="module")
def avatar(tmp_path_factory):
    return write_avatar_zip(tmp_path_factory.mktemp("codings") / "avatar.zip", AvatarSpec(subdivided=True))


def test_codings_end_to_end(avatar, tmp_path, monkeypatch):
    """Every probe row of every per-Gaussian buffer and the morph basis, and a budget row: finite numbers, and the
    row of compact's own coding draws compact's own frames (the rewritten bundle changes nothing else)."""
    monkeypatch.setattr(codings, "SIZE", 64)
    monkeypatch.setattr(codings, "FRAMES", 3)
    monkeypatch.setattr(codings, "CODEBOOK_SIZES", (8,))
    out = tmp_path / "bench"
    result = CliRunner().invoke(app, ["codings", str(avatar), "--budgets", "50", "--combined-loss-db", "3",
                                      "--out", str(out)])
    assert result.exit_code == 0, result.output
    report = json.loads((out / "codings.json").read_text())
    rows = report["probes"]
    buffers = {row["buffer"] for row in rows}
    # (the tiny avatar's opacities are all one value, which its graph holds as a constant)
    assert {"deform/rest_points", "deform/rotation", "deform/log_scale", "deform/sh_dc", "deform/morph_basis"} \
        <= buffers
    for buffer in buffers:
        codings_of = {row["coding"] for row in rows if row["buffer"] == buffer}
        assert "as compact stores it" in codings_of and len(codings_of) >= 3, (buffer, codings_of)
    assert any(row["coding"] == "vq8" for row in rows) and any("spatial order" in row["coding"] for row in rows)
    own = [row for row in rows if row["coding"] == "as compact stores it"]
    assert all(row["head_psnr_min_db"] == report["compact_head_psnr"][0] for row in own)
    for row in rows:
        assert min(row["bytes"], row["zlib_bytes"], row["lzma_bytes"]) > 0 and not math.isnan(row["head_psnr_min_db"])
        assert row["head_psnr_min_db"] <= row["head_psnr_median_db"]
    combined = report["combined"]  # each buffer's smallest coding within the loss, all at once
    for buffer, coding in combined["codings"].items():
        (alone,) = [row for row in rows if (row["buffer"], row["coding"]) == (buffer, coding)]
        assert alone["head_psnr_min_db"] >= report["compact_head_psnr"][0] - 3
    saved = sum(next(r["bytes"] for r in own if r["buffer"] == b) - next(
        r["bytes"] for r in rows if (r["buffer"], r["coding"]) == (b, c)) for b, c in combined["codings"].items())
    assert combined["bytes"] == report["compact_bytes"] - saved and not math.isnan(combined["head_psnr_min_db"])
    (budget,) = report["budgets"]
    assert budget["budget"] == 0.5 and 0 < budget["bytes"] < report["compact_bytes"]
    assert "| budget |" in (out / "codings.md").read_text()


@pytest.mark.slow  # two torch.onnx exports of a speaker with a translator: ~30 s
def test_codings_of_a_speaker_checkpoint(tmp_path, monkeypatch):
    """A FLAME speaker with a translator (a tiny demo speaker's checkpoint): driven by the sample speech, its
    per-Gaussian buffers probed (no spatial order: its rest points are a mesh's, not the Gaussians')."""
    from gaussiantalker.exporter.demo.demo_speaker import make_demo_speaker
    from gaussiantalker.exporter.export.checkpoint import save_checkpoint

    speaker, _ = make_demo_speaker(n_gaussians=300, seed=3, train_seconds=0, progress=False)
    save_checkpoint(speaker, tmp_path / "demo.ckpt")
    monkeypatch.setattr(codings, "SIZE", 64)
    monkeypatch.setattr(codings, "FRAMES", 2)
    monkeypatch.setattr(codings, "CODEBOOK_SIZES", (8,))
    out = tmp_path / "bench"
    result = CliRunner().invoke(app, ["codings", str(tmp_path / "demo.ckpt"), "--out", str(out)])
    assert result.exit_code == 0, result.output
    rows = json.loads((out / "codings.json").read_text())["probes"]
    assert {"deform/log_scale", "deform/barycentric"} <= {row["buffer"] for row in rows}
    assert not any("spatial order" in row["coding"] for row in rows)
