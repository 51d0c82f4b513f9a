"""Command line end to end in a temp dir: make a (small) demo speaker -> gt-export --verify -> play -> mp4.

A failing --verify (exit 1, the good bundle kept, the new one as NAME.unverified.gtb) is tested in-process, with
the ONNX export replayed, by tests/test_stability_files.py::test_failed_verify_keeps_the_real_good_bundle.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from gaussiantalker.sdk.video import probe_video

ROOT = Path(__file__).resolve().parents[1]
GT_EXPORT = [sys.executable, "-m", "gaussiantalker.exporter.cli"]


def _run(args, cwd, expect=0):
    result = subprocess.run(args, cwd=cwd, capture_output=True, text=True, check=False)
    assert result.returncode == expect, f"{args} -> {result.returncode}\n{result.stdout}\n{result.stderr}"
    return result


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    work = tmp_path_factory.mktemp("cli")
    _run([sys.executable, str(ROOT / "samples" / "make_demo_speaker.py"), "-o", "speaker.ckpt", "--gaussians", "3000",
          "--train-seconds", "0", "-q"], work)  # untrained: these tests are about the command line
    return work


def test_export_verify_play(workdir):
    out = _run(GT_EXPORT + ["speaker.ckpt", "-o", "speaker.gtb", "--verify", "--report", "report.json",
                            "--resolution", "96", "-q"], workdir)
    assert "verification PASSED" in out.stdout
    report = json.loads((workdir / "report.json").read_text())
    assert report["passed"] is True
    assert len(report["frames"]) == 25 and all("psnr_db" in f for f in report["frames"])
    assert report["min_psnr_db"] >= 50.0
    assert set(report["graphs"]) == {"translator", "deform"}
    assert all("max_abs_err" in g for g in report["graphs"].values())
    assert (workdir / "speaker.gtb").is_file()
    assert not list(workdir.glob(".*unverified*"))

    audio = workdir / "speech.wav"
    shutil.copy(ROOT / "samples" / "demo_speech.wav", audio)  # 10.0 s at 16 kHz -> 250 frames at 25 fps
    _run([sys.executable, str(ROOT / "samples" / "play.py"), "speaker.gtb", "--audio", str(audio), "-o", "talk.mp4",
          "--resolution", "128", "-q"], workdir)
    info = probe_video(workdir / "talk.mp4")
    assert info["frames"] == 250
    assert info["has_audio"]


def test_bad_input_gives_clear_errors(workdir):
    out = _run(GT_EXPORT + ["missing.ckpt"], workdir, expect=2)
    assert "error: checkpoint missing.ckpt does not exist" in out.stderr
    out = _run(GT_EXPORT + ["speaker.ckpt", "-o", "x.gtb", "--codec", "zip9"], workdir, expect=2)
    assert "unknown buffer codec 'zip9'" in out.stderr
    assert not (workdir / "x.gtb").exists()
    (workdir / "broken.gtb").write_bytes(b"GTBUNDLE" + b"\0" * 10)
    out = _run([sys.executable, str(ROOT / "samples" / "play.py"), "broken.gtb", "--audio", "nothing.wav",
                "-o", "x.mp4"], workdir, expect=2)
    assert "error:" in out.stderr and "truncated" in out.stderr
