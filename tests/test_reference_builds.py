"""Builds of the demo speaker and a bench on a speaker with a reference clip.

* The demo trainings stop on step counts, never on the wall clock (docs/demo-speaker.md, "Identical builds"): two
  builds with one seed give bit-identical inpainter weights even when the clock runs 1000x fast between them,
  another seed does not, and the translator runs its steps whatever the clock; the former time budgets
  (`--inpaint-seconds`, `--train-seconds`, their keywords) map to fixed step counts and say so once. Tiny
  trainings (a few steps, a 192x240 clip): seconds each.
* `gt-bench video` on the session's composited bundle (`clip_export`): the bare head by default, every output; the
  composited frames with `composite=True`, the outputs without alpha.
"""

from __future__ import annotations

import importlib.util
import itertools
import re
import types
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

ROOT = Path(__file__).resolve().parents[1]
CLIP_SIZE = (192, 240)  # width, height: a small clip whose mask crops still hold F's 96-pixel training patches


def _racing_clock(module, monkeypatch) -> None:
    """Make `module`'s clock run 1000 s per reading: a training that stopped on the wall clock would stop at once."""
    ticks = itertools.count()
    monkeypatch.setattr(module, "time", types.SimpleNamespace(perf_counter=lambda: 1000.0 * next(ticks)))


@pytest.fixture(scope="module")
def tiny_speaker():
    from gaussiantalker.exporter.demo.demo_speaker import make_demo_speaker

    speaker, _ = make_demo_speaker(n_gaussians=300, seed=3, train_steps=0, progress=False)
    speaker.pose_track = speaker.pose_track[:4].clone()
    return speaker


def _inpainter_weights(speaker, seed: int, steps: int = 2) -> dict:
    from gaussiantalker.exporter.demo.clip import ClipComposer
    from gaussiantalker.exporter.demo.train_inpainter import train_demo_inpainter

    composer = ClipComposer(speaker, size=CLIP_SIZE)  # a fresh composer, as a new build makes
    try:
        model, metrics = train_demo_inpainter(composer, pairs=1, steps=steps, seed=seed, progress=False)
    finally:
        composer.splatter.release()
    assert metrics["inpaint_steps"] == steps
    return {name: value.clone() for name, value in model.state_dict().items()}


def _same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[name], b[name]) for name in a)


def test_two_inpainter_builds_with_one_seed_are_identical(tiny_speaker, monkeypatch):
    from gaussiantalker.exporter.model import inpainter

    first = _inpainter_weights(tiny_speaker, seed=0)
    torch.manual_seed(123)  # whatever ran before: F's initial weights come from the build's seed
    _racing_clock(inpainter, monkeypatch)
    again = _inpainter_weights(tiny_speaker, seed=0)
    assert _same(first, again)
    assert not _same(first, _inpainter_weights(tiny_speaker, seed=1))  # the comparison can fail


def test_the_translator_stops_on_its_step_count(monkeypatch):
    """make_demo_speaker hands the translator a step count and no time budget, and training with no budget runs
    its steps however fast the clock runs (its steps, seed and settings make the same weights: the module's
    docstring)."""
    from gaussiantalker.exporter.demo import demo_speaker, train_translator
    from gaussiantalker.exporter.model.translator import MotionTranslator, TranslatorConfig

    handed: list[tuple] = []
    monkeypatch.setattr(demo_speaker, "train_demo_translator",
                        lambda model, n_expr, **kwargs: handed.append(kwargs) or {})
    demo_speaker.make_demo_speaker(n_gaussians=30, progress=False)
    demo_speaker.make_demo_speaker(n_gaussians=30, progress=False, train_steps=7)
    assert [(k["settings"].max_steps, "seconds_budget" in k) for k in handed] == [(400, False), (7, False)]

    _racing_clock(train_translator, monkeypatch)
    settings = train_translator.TrainSettings(max_steps=2, batch_size=1, crop_frames=25, n_clips=2, warmup_steps=1,
                                              heldout_seconds=1.0)
    torch.manual_seed(0)
    metrics = train_translator.train_demo_translator(MotionTranslator(TranslatorConfig(), 20), 20, seed=0,
                                                     progress=False, settings=settings)
    assert metrics["steps"] == 2 and metrics["stop_reason"] == "max_steps"


def test_former_time_budgets_map_to_steps_and_say_so_once(monkeypatch):
    from gaussiantalker.exporter.demo import steps

    monkeypatch.setattr(steps, "_told", set())
    with pytest.warns(FutureWarning, match=r"seconds=3 is read as steps=30"):
        assert steps.training_steps(None, 3.0, 600, names=("steps", "seconds")) == 30
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # once: the second use is silent, as are exact mappings
        assert steps.training_steps(None, 5.0, 600, names=("steps", "seconds")) == 50
        assert steps.training_steps(None, 0.0, 600, names=("other_steps", "other")) == 0
        assert steps.training_steps(None, float("inf"), 400, names=("t", "t_s"), cap=400) == 400
        assert steps.training_steps(7, None, 600, names=("steps", "seconds")) == 7
        assert steps.training_steps(None, None, 600, names=("steps", "seconds")) == 600
    with pytest.raises(ValueError, match="not both"):
        steps.training_steps(7, 3.0, 600, names=("steps", "seconds"))
    with pytest.raises(ValueError, match="step count"):
        steps.steps_for_seconds(float("inf"))


def _demo_cli(monkeypatch) -> tuple[object, list[dict]]:
    """samples/make_demo_speaker.py's app with the build and the save recorded instead of run."""
    spec = importlib.util.spec_from_file_location("sample_make_demo_speaker", ROOT / "samples" / "make_demo_speaker.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    calls: list[dict] = []

    def build(gaussians, **kwargs):
        calls.append(kwargs)
        return None, {}

    monkeypatch.setattr(module, "make_demo_speaker", build)
    monkeypatch.setattr(module, "save_checkpoint", lambda speaker, path: None)
    return module.app, calls


@pytest.mark.parametrize(("args", "train", "inpaint", "note"), [
    ([], None, None, ""),
    (["--inpaint-seconds", "3", "--train-seconds", "0"], 0, 30, "--inpaint-seconds 3 is read as --inpaint-steps 30"),
    (["--train-seconds", "20"], 200, None, "--train-seconds 20 is read as --train-steps 200"),
    (["--train-seconds", "150"], 400, None, "--train-seconds 150 is read as --train-steps 400"),
    (["--train-steps", "5", "--inpaint-steps", "7"], 5, 7, ""),
])
def test_the_cli_takes_steps_and_its_former_seconds(monkeypatch, args, train, inpaint, note):
    app, calls = _demo_cli(monkeypatch)
    result = CliRunner().invoke(app, ["-o", "unused.ckpt", "-q", *args])
    assert result.exit_code == 0, (result.output, result.exception)
    assert (calls[0]["train_steps"], calls[0]["inpaint_steps"]) == (train, inpaint)
    assert (note in result.stderr) if note else not result.stderr, result.stderr


def test_the_cli_refuses_steps_and_seconds_together(monkeypatch):
    app, calls = _demo_cli(monkeypatch)
    result = CliRunner().invoke(app, ["-o", "unused.ckpt", "--inpaint-steps", "5", "--inpaint-seconds", "3"])
    assert result.exit_code == 2 and "not both" in result.output + result.stderr and not calls


# -- gt-bench video on a composited bundle ----------------------------------------------------------------------
ROW = re.compile(r"^\| (.+?) \| (\d+) \| (\d+\.\d) \| (\d+) \|$")


def _rows(output: str) -> dict[str, tuple]:
    return {m.group(1): m.groups()[1:] for m in map(ROW.match, output.splitlines()) if m}


def test_gt_bench_video_measures_a_composited_bundle(clip_export, capsys):
    from tools.bench.app import app
    from tools.bench.video_outputs import OUTPUTS, run_video_bench

    result = CliRunner().invoke(app, ["video", str(clip_export.path), "--size", "48", "--frames", "3",
                                      "--rounds", "1"])
    assert result.exit_code == 0, (result.output, result.exception)
    first = result.output.splitlines()[0]
    assert "the bare head, RGBA (its reference clip unused" in first and "48x48" in first, first
    assert set(_rows(result.output)) == {"mp4 h264 via imageio-ffmpeg (ffmpeg process)", *(o[0] for o in OUTPUTS)}

    run_video_bench(clip_export.path, size=48, frames=3, rounds=1, composite=True)
    output = capsys.readouterr().out
    first = output.splitlines()[0]
    width, height = clip_export.speaker.reference.layout.size
    assert "composited into the reference clip, RGB" in first, first
    assert f"{2 * round(48 * width / height / 2)}x48" in first, first  # the clip's aspect, an even width
    rows = _rows(output)
    assert set(rows) == {"mp4 h264 via imageio-ffmpeg (ffmpeg process)",
                         *(o[0] for o in OUTPUTS if not o[2].get("alpha"))}
    assert all(int(kb) > 0 for _, _, kb in rows.values())
    assert np.isfinite([float(ms) for _, ms, _ in rows.values()]).all()
