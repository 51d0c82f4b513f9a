"""Train the built-in voice drivers and measure them: `python samples/train_voice.py` (docs/voice.md).

Speaks the training sentences with espeak-ng, festival and flite (`apt-get install espeak-ng festival
festvox-us-slt-hts flite`), trains the audio -> ARKit network on
their phoneme targets for a fixed number of steps, writes the ARKit model and the FLAME model built on the same
network (exporter/voice/models/ by default), then measures the ARKit model on held-out voices and sentences and
writes the bench (docs/bench/voice/ by default). Everything random comes from --seed; the run is a fixed number
of steps on one thread, so the same command on the same machine writes the same files.
"""

from __future__ import annotations

import json
import shlex
import time
from pathlib import Path

import torch
import typer

from gaussiantalker.exporter.voice import corpus, espeak, evaluate, festival, flame_fit, flite, onnx_graph
from gaussiantalker.exporter.voice.data import speak
from gaussiantalker.exporter.voice.model import VoiceConfig, VoiceNet
from gaussiantalker.exporter.voice.train import TrainSettings, train, training_streams

app = typer.Typer(add_completion=False)
MODELS = Path(__file__).resolve().parent.parent / "src" / "gaussiantalker" / "exporter" / "voice" / "models"
BENCH = Path(__file__).resolve().parent.parent / "docs" / "bench" / "voice"


def _write(path: Path, data: bytes) -> None:
    """Write through a temporary file, so a killed run never leaves half a model."""
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.name + ".partial")
    partial.write_bytes(data)
    partial.replace(path)


@app.command()
def main(
    out_dir: Path = typer.Option(MODELS, "--out-dir", help="where arkit_voice.onnx and flame_voice.onnx go"),
    bench_dir: Path = typer.Option(BENCH, "--bench-dir", help="where voice.json and voice.md go"),
    steps: int = typer.Option(TrainSettings.steps, "--steps", min=1, help="training steps"),
    utterances: int = typer.Option(TrainSettings.utterances, "--utterances", min=8,
                                   help="espeak-ng training utterances"),
    natural: int = typer.Option(TrainSettings.natural_utterances, "--natural", min=0,
                                help="festival and flite training utterances (English)"),
    world: int = typer.Option(TrainSettings.world_utterances, "--world", min=0,
                              help="festival's Italian, Czech, Finnish and Catalan training utterances"),
    batch_size: int = typer.Option(TrainSettings.batch_size, "--batch-size", min=1),
    closure_weight: float = typer.Option(TrainSettings.closure_weight, "--closure-weight", min=0.0,
                                         help="weight of lips left open at /p b m/ in the loss"),
    band_masks: float = typer.Option(TrainSettings.band_masks, "--band-masks", min=0.0, max=1.0,
                                     help="share of training crops whose log-mel bands are masked"),
    band_colour: float = typer.Option(TrainSettings.band_colour, "--band-colour", min=0.0, max=1.0,
                                      help="share of training crops whose log-mel bands are coloured"),
    heldout: int = typer.Option(60, "--heldout", min=1, help="held-out clips (training languages)"),
    unseen: int = typer.Option(16, "--unseen", min=0, help="held-out clips in a language never trained on"),
    seed: int = typer.Option(0, "--seed", help="seed of everything random"),
    weights: Path | None = typer.Option(None, "--weights", help="load network weights saved by --save-weights "
                                        "instead of training (re-export and re-measure a run)"),
    save_weights: Path | None = typer.Option(None, "--save-weights", help="also save the network weights here"),
    resume: Path | None = typer.Option(None, "--resume", help="save the training state here as it goes; a run "
                                       "started again with the same file and options goes on from it"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="no progress bars"),
) -> None:
    """Train (or load), export and measure the voice drivers; print the headline figures."""
    if not espeak.available():
        typer.echo("error: espeak-ng's library is not installed (apt-get install espeak-ng)", err=True)
        raise typer.Exit(2)
    missing = [f"{engine}:{voice}" for engine, voices in corpus.TRAIN_FAMILIES.values() for voice in voices
               if natural and not {"festival": festival, "flite": flite}[engine].available(voice)]
    if missing:
        typer.echo(f"error: training voices missing: {', '.join(missing)} (apt-get install festival "
                   "festvox-us-slt-hts flite; or --natural 0)", err=True)
        raise typer.Exit(2)
    missing = [voice for voice in corpus.WORLD_FAMILY[2] if world and not festival.available(voice)]
    if missing:
        packages = " ".join(sorted({festival.VOICE_TABLE[voice].package for voice in missing}))
        typer.echo(f"error: festival's voices {', '.join(missing)} are missing (apt-get install {packages}; "
                   "or --world 0)", err=True)
        raise typer.Exit(2)
    settings = TrainSettings(steps=steps, utterances=utterances, natural_utterances=natural,
                             world_utterances=world, batch_size=batch_size,
                             closure_weight=closure_weight, band_masks=band_masks, band_colour=band_colour)
    times: dict[str, float] = {}
    start = time.perf_counter()
    if weights is None:
        streams = training_streams(settings, seed, progress=not quiet)
        times["speak_seconds"] = round(time.perf_counter() - start, 1)
        model, record = train(streams, settings, seed, progress=not quiet, resume=resume)
        times["train_seconds"] = record.pop("train_seconds")
        del streams
    else:  # the run that saved these weights (its record beside them, when it wrote one)
        model = VoiceNet(VoiceConfig(channels=settings.channels))
        model.load_state_dict(torch.load(weights, weights_only=True))
        model.eval()
        saved = weights.with_name(weights.name + ".json")
        record = json.loads(saved.read_text()) if saved.is_file() else {"weights": str(weights)}
        times = record.pop("times", times)
    if save_weights is not None:
        torch.save(model.state_dict(), save_weights)
        save_weights.with_name(save_weights.name + ".json").write_text(json.dumps({**record, "times": times}))
    doc = f"GaussianTalker voice driver (docs/voice.md), seed {seed}, {settings.steps} steps"
    arkit = onnx_graph.arkit_model(model, doc).SerializeToString()
    flame = onnx_graph.flame_model(model, *flame_fit.default_maps(), doc=doc).SerializeToString()
    _write(out_dir / "arkit_voice.onnx", arkit)
    _write(out_dir / "flame_voice.onnx", flame)
    start = time.perf_counter()
    training = corpus.training_specs(settings.utterances, seed)
    clips = [evaluate.make_clip(u) for u in speak(corpus.heldout_specs(heldout, seed, training=training),
                                                  progress=not quiet, desc="held-out")]
    foreign = [evaluate.make_clip(u) for u in speak(corpus.heldout_specs(unseen, seed, corpus.UNSEEN_LANGUAGES,
                                                                         training), progress=not quiet,
                                                    desc="unseen language")]
    result = evaluate.evaluate(arkit, clips, foreign)
    times["evaluate_seconds"] = round(time.perf_counter() - start, 1)
    chosen = {"--steps": (steps, TrainSettings.steps), "--utterances": (utterances, TrainSettings.utterances),
              "--natural": (natural, TrainSettings.natural_utterances),
              "--world": (world, TrainSettings.world_utterances),
              "--batch-size": (batch_size, TrainSettings.batch_size),
              "--closure-weight": (closure_weight, TrainSettings.closure_weight),
              "--band-masks": (band_masks, TrainSettings.band_masks),
              "--band-colour": (band_colour, TrainSettings.band_colour), "--heldout": (heldout, 60),
              "--unseen": (unseen, 16), "--seed": (seed, 0)}
    command = shlex.join(["python", "samples/train_voice.py"] + [
        part for flag, (value, default) in chosen.items() if value != default for part in (flag, str(value))])
    evaluate.write_report(result, bench_dir, command, {**record, **times})
    main_result = result["heldout"]
    typer.echo(json.dumps({
        "agreement_r": {k: round(v, 3) for k, v in main_result["agreement_r"].items()},
        "closure_share": round(main_result["model"]["closure_share"], 3),
        "jaw_loudness_r": round(main_result["model"]["jaw_loudness_r_median"], 3),
        "lag_ms": round(main_result["model"]["lag_ms_median"], 1),
        "model_mb": round(len(arkit) / 1e6, 2), **times,
        "ms_per_audio_second": round(1000 * result["cpu"]["seconds_per_audio_second"], 2),
    }, indent=2, default=float))
    typer.echo(f"wrote {out_dir / 'arkit_voice.onnx'}, {out_dir / 'flame_voice.onnx'}, {bench_dir}")


if __name__ == "__main__":
    app()
