"""Command line end to end in a temp dir: make a (small) demo speaker -> gt-export --verify -> play -> mp4.

In-process (typer's CliRunner on the gt-export app and the sample scripts' apps, the session's recorded ONNX graphs
rebound to the exported speaker instead of torch.onnx) for the quick run, with a quick start of the installed
`gt-export` console script; the same flow in subprocesses, as a user runs it, is `heavy` (CI runs it as commands in
.ci/runtime-only: make_demo_speaker.py, gt-export and play.py, the last in a runtime-only install).

A failing --verify (exit 1, the good bundle kept, the new one as NAME.unverified.gtb) is tested in-process, with
the ONNX export replayed, by tests/test_stability_files.py::test_failed_verify_keeps_the_real_good_bundle.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
import wave
from pathlib import Path

import pytest
from typer.testing import CliRunner

from gaussiantalker.sdk.video import probe_video

ROOT = Path(__file__).resolve().parents[1]
GT_EXPORT = [sys.executable, "-m", "gaussiantalker.cli.export"]
# An untrained 2k-Gaussian demo speaker: another speaker of the session's small speaker's architecture.
SAMPLE_SPEAKER_ARGS = ["--gaussians", "2000", "--seed", "5", "--train-steps", "0", "--no-reference"]


def _run(args, cwd, expect=0, env=None):
    result = subprocess.run(args, cwd=cwd, capture_output=True, text=True, check=False, env=env)
    assert result.returncode == expect, f"{args} -> {result.returncode}\n{result.stdout}\n{result.stderr}"
    return result


def _sample_app(name: str):
    """The typer app of samples/NAME.py (a script, not a package module)."""
    spec = importlib.util.spec_from_file_location(f"sample_{name}", ROOT / "samples" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.app


def _invoke(app, args, expect=0):
    result = CliRunner().invoke(app, [str(a) for a in args])
    assert result.exit_code == expect, (f"{args} -> {result.exit_code}\n{result.stdout}\n{result.stderr}\n"
                                        f"{result.exception!r}")
    return result


def _check_verified_export(out: str, work: Path, composited: bool = False) -> None:
    """What `gt-export speaker.ckpt -o speaker.gtb --verify --report report.json` must leave and say (with the
    `inpaint` graph and the composited frames for a speaker with a reference clip)."""
    assert "verification PASSED" in out
    report = json.loads((work / "report.json").read_text())
    assert report["passed"] is True
    assert len(report["frames"]) == 25 and all("psnr_db" in f for f in report["frames"])
    assert report["min_psnr_db"] >= 50.0
    assert set(report["graphs"]) == {"translator", "translator_stream", "translator_stream_steady", "deform"} | (
        {"inpaint"} if composited else set())
    assert ("composited" in report) == composited
    if composited:
        assert report["composited"]["passed"] and report["composited"]["min_psnr_db"] >= 50.0
        assert "composited: 12 frames" in out
    assert all("max_abs_err" in g for g in report["graphs"].values())
    assert (work / "speaker.gtb").is_file()
    assert not list(work.glob("*unverified*")) and not list(work.glob(".*"))


def _check_video(path: Path, frames: int = 250) -> None:
    info = probe_video(path)
    assert info["frames"] == frames  # demo_speech.wav: 10.0 s at 16 kHz -> 250 frames at 25 fps
    assert info["has_audio"]


def _speech_clip(path: Path, seconds: float) -> Path:
    """The first `seconds` of samples/demo_speech.wav, as the same kind of wav file."""
    with wave.open(str(ROOT / "samples" / "demo_speech.wav"), "rb") as source:
        params, data = source.getparams(), source.readframes(int(seconds * source.getframerate()))
    with wave.open(str(path), "wb") as clip:
        clip.setparams(params)
        clip.writeframes(data)
    return path


# -- in-process ---------------------------------------------------------------------------------------------------


@pytest.fixture
def in_process_dir(tmp_path, monkeypatch, small_export, rebind_onnx_exports):
    """A temp dir (the cwd) holding speaker.ckpt from samples/make_demo_speaker.py; gt-export rebinds the session's
    recorded ONNX graphs to the speaker it loads instead of running torch.onnx (--verify would catch a bundle
    that is not that speaker's)."""
    monkeypatch.chdir(tmp_path)
    _invoke(_sample_app("make_demo_speaker"), ["-o", "speaker.ckpt", *SAMPLE_SPEAKER_ARGS, "-q"])
    rebind_onnx_exports(small_export)
    return tmp_path


def test_export_verify_play_in_process(in_process_dir):
    from gaussiantalker.cli.export import app

    work = in_process_dir
    result = _invoke(app, ["speaker.ckpt", "-o", "speaker.gtb", "--verify", "--report", "report.json",
                           "--resolution", "96", "-q"])
    assert ("2000 Gaussians, tier fp32, graphs: translator, translator_stream, translator_stream_steady, deform"
            in result.stdout)
    assert "bundle: speaker.gtb (verified)" in result.stdout
    _check_verified_export(result.stdout, work)

    _speech_clip(work / "speech.wav", 2.0)  # 50 frames, as the subprocess test plays
    result = _invoke(_sample_app("play"), ["speaker.gtb", "--audio", "speech.wav", "-o", "talk.mp4",
                                           "--resolution", "128", "-q"])
    assert "wrote talk.mp4 (50 frames, 2.0 s of audio)" in result.stdout
    _check_video(work / "talk.mp4", frames=50)


def test_export_verify_composited_in_process(clip_export, replay_onnx_exports, tmp_path, monkeypatch):
    """A speaker with a reference clip (the session's small clip speaker): --verify adds the inpaint graph and the
    composited frames to what it checks and reports (its recorded graphs replayed instead of torch.onnx)."""
    from gaussiantalker.cli.export import app

    monkeypatch.chdir(tmp_path)
    shutil.copy(clip_export.checkpoint, tmp_path / "speaker.ckpt")
    replay_onnx_exports(clip_export.protos)
    result = _invoke(app, ["speaker.ckpt", "-o", "speaker.gtb", "--verify", "--report", "report.json",
                           "--resolution", "96", "-q"])
    _check_verified_export(result.stdout, tmp_path, composited=True)


def test_bad_input_gives_clear_errors_in_process(in_process_dir):
    from gaussiantalker.cli.export import app

    result = _invoke(app, ["missing.ckpt"], expect=2)
    assert "error: checkpoint missing.ckpt does not exist" in result.stderr
    result = _invoke(app, ["speaker.ckpt", "-o", "x.gtb", "--codec", "zip9"], expect=2)
    assert "unknown codec 'zip9'" in result.stderr
    known = "quality, balanced, compact, fast, mobile"
    for args, message in ((["--preset", "tiny"], f"unknown preset 'tiny' (known: {known})"),
                          (["--preset", "fast", "--codec", "fp16"], "give --preset or --codec, not both"),
                          (["--flame-codec", "q4/x"], "only q16/q8/q4 take a chunk size"),
                          (["--inpaint-codec", "q9"], "inpaint: unknown codec 'q9'"),
                          (["--reference-codec", "crf:60"],
                           "reference clip setting 'crf:60': an H.264 CRF must be an integer 0..51"),
                          (["--gaussian-budget", "lots"], "--gaussian-budget must be a whole number or a percentage")):
        result = _invoke(app, ["speaker.ckpt", "-o", "x.gtb", *args], expect=2)
        assert message in result.stderr + result.stdout, args
    assert not (in_process_dir / "x.gtb").exists()
    (in_process_dir / "broken.gtb").write_bytes(b"GTBUNDLE" + b"\0" * 10)
    result = _invoke(_sample_app("play"), ["broken.gtb", "--audio", "nothing.wav", "-o", "x.mp4"], expect=2)
    assert "error:" in result.stderr and "truncated" in result.stderr


def _console_script() -> str:
    script = shutil.which("gt-export", path=str(Path(sys.executable).parent)) or shutil.which("gt-export")
    if script is None:
        pytest.skip("the gt-export console script is not installed (pip install -e .)")
    return script


def test_console_script_starts(tmp_path):
    """The installed `gt-export` runs its entry point; here as in a runtime-only install (the export extra's modules
    made unimportable, so nothing heavy loads): exit 2 and one line naming them."""
    from gaussiantalker.cli.extras import EXPORT_EXTRA_MODULES

    blocked = tmp_path / "blocked"
    for name in EXPORT_EXTRA_MODULES:
        (blocked / name).mkdir(parents=True)
        (blocked / name / "__init__.py").write_text(f"raise ImportError('{name} hidden by the test')\n")
    env = os.environ | {"PYTHONPATH": os.pathsep.join(filter(None, [str(blocked), os.environ.get("PYTHONPATH")]))}
    result = _run([_console_script(), "speaker.ckpt"], tmp_path, expect=2, env=env)
    assert result.stdout == ""
    assert result.stderr.startswith(f"gt-export: needs the 'export' extra ({', '.join(EXPORT_EXTRA_MODULES)} not "
                                    "installed)") and len(result.stderr.splitlines()) == 1


@pytest.mark.slow  # ~2.5 s: the real script imports torch; test_console_script_starts is the quick check
def test_console_script_runs(tmp_path):
    """The installed `gt-export` reports a bad argument with exit 2 and one clear line."""
    result = _run([_console_script(), "missing.ckpt"], tmp_path, expect=2)
    assert result.stderr.strip() == "error: checkpoint missing.ckpt does not exist"


# -- subprocesses, as a user runs them (slow: each one imports torch) ---------------------------------------------


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    work = tmp_path_factory.mktemp("cli")
    # An untrained bare-head speaker: these tests are about the command line, as a user runs it (the composited
    # --verify that a reference clip adds is test_export_verify_composited_in_process's).
    _run([sys.executable, str(ROOT / "samples" / "make_demo_speaker.py"), "-o", "speaker.ckpt",
          *SAMPLE_SPEAKER_ARGS, "-q"], work)
    return work


@pytest.mark.heavy  # torch.onnx and the player in subprocesses (~40 s); test_export_verify_play_in_process and
# .ci/runtime-only cover the same in CI
def test_export_verify_play(workdir):
    out = _run(GT_EXPORT + ["speaker.ckpt", "-o", "speaker.gtb", "--verify", "--report", "report.json",
                            "--resolution", "96", "-q"], workdir)
    _check_verified_export(out.stdout, workdir)

    audio = _speech_clip(workdir / "speech.wav", 2.0)  # 50 frames: the whole path; long audio has tests of its own
    _run([sys.executable, str(ROOT / "samples" / "play.py"), "speaker.gtb", "--audio", str(audio), "-o", "talk.mp4",
          "--resolution", "128", "-q"], workdir)
    _check_video(workdir / "talk.mp4", frames=50)


@pytest.mark.heavy  # three subprocesses; test_bad_input_gives_clear_errors_in_process checks the same in-process
def test_bad_input_gives_clear_errors(workdir):
    out = _run(GT_EXPORT + ["missing.ckpt"], workdir, expect=2)
    assert "error: checkpoint missing.ckpt does not exist" in out.stderr
    out = _run(GT_EXPORT + ["speaker.ckpt", "-o", "x.gtb", "--codec", "zip9"], workdir, expect=2)
    assert "unknown codec 'zip9'" in out.stderr
    assert not (workdir / "x.gtb").exists()
    (workdir / "broken.gtb").write_bytes(b"GTBUNDLE" + b"\0" * 10)
    out = _run([sys.executable, str(ROOT / "samples" / "play.py"), "broken.gtb", "--audio", "nothing.wav",
                "-o", "x.mp4"], workdir, expect=2)
    assert "error:" in out.stderr and "truncated" in out.stderr
