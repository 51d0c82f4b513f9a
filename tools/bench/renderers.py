"""`gt-bench renderers`: the CPU tile splatter against the GL splatter, side by side on the same frame.

One neutral frame of the demo speaker (untrained: its Gaussians, not its motion, set the cost) per Gaussian count,
prepared once per splatter (the depth sort is the same numpy for both) and drawn `frames` times per round; rounds
alternate GL, CPU at each thread count, so a busy machine slows all of them alike. Reported per size: medians of
the splat time after preparing (GL: upload + draw + readback, with the vertex work; CPU: projection and binning +
tile blending + conversion), and the ratio GL / CPU (> 1: the CPU splatter is faster).

With `--play BUNDLE` it also times the whole path a user runs, per renderer, alternating: audio -> pixels
(`TalkingHead.frames` on the sample speech, in one process: the head is made once per renderer, frames timed) and
`samples/play.py` end to end (interpreter, imports, bundle load, the JIT cache load, render, encoding), bare at
`--play-size` and composited at the clip's size.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import typer

SPLAT_STAGES = ("upload", "draw", "readback")


def neutral_gaussians(speaker, camera) -> tuple[np.ndarray, ...]:
    """(means, cov3d, rgb, opacity) of the speaker's neutral frame seen from `camera`, as numpy."""
    with torch.no_grad():
        means, cov3d, rgb, opacity = speaker.deform(
            torch.zeros(1, speaker.config.n_expr), torch.zeros(1, 15), torch.zeros(1, 3),
            torch.as_tensor(camera.center, dtype=torch.float32)[None])
    return means[0].numpy(), cov3d[0].numpy(), rgb[0].numpy(), opacity.reshape(-1).numpy()


def _splat_ms(splatter, prepared, frames: int) -> list[float]:
    """Splat times (ms) of `frames` draws of one prepared frame."""
    times = []
    for _ in range(frames):
        splatter.draw(prepared, (1.0, 1.0, 1.0))
        times.append(1000.0 * sum(splatter.last_timings[stage] for stage in SPLAT_STAGES))
    return times


def run_renderers_bench(gaussians: str, sizes: str, frames: int, rounds: int, threads: str) -> dict:
    """Bench GL against the CPU splatter at every (Gaussian count, size) and CPU thread count; print and return
    the results (`gt-bench renderers --json` writes them)."""
    import numba

    from gaussiantalker.exporter.demo.demo_speaker import make_demo_speaker
    from gaussiantalker.runtime.splat.cpu import CPUSplatter
    from gaussiantalker.runtime.splat.gl import GLSplatter

    from .frames import machine_info

    thread_counts = [min(int(t), numba.config.NUMBA_NUM_THREADS) for t in threads.split(",")]
    gl = GLSplatter()
    cpus = {t: CPUSplatter(threads=t) for t in thread_counts}
    results = {"machine": machine_info(), "numba": numba.__version__, "frames": frames, "rounds": rounds,
               "runs": []}
    try:
        for count in (int(g) for g in gaussians.split(",")):
            speaker, _ = make_demo_speaker(count, train_seconds=0, progress=False)
            for size in (int(s) for s in sizes.split(",")):
                camera = speaker.camera.resized(size, size)
                arrays = neutral_gaussians(speaker, camera)
                prepared = {"gl": gl.prepare(*arrays, camera)}
                for t, cpu in cpus.items():
                    prepared[f"cpu{t}"] = cpu.prepare(*arrays, camera)
                splatters = {"gl": gl, **{f"cpu{t}": cpu for t, cpu in cpus.items()}}
                for name, splatter in splatters.items():  # warm: buffers, framebuffers, first-touch pages
                    _splat_ms(splatter, prepared[name], 1)
                times: dict[str, list[float]] = {name: [] for name in splatters}
                for _ in range(rounds):
                    for name, splatter in splatters.items():
                        times[name] += _splat_ms(splatter, prepared[name], frames)
                medians = {name: float(np.median(values)) for name, values in times.items()}
                run = {"gaussians": count, "size": size, "splat_ms": medians,
                       "gl_over_cpu": {name: medians["gl"] / ms for name, ms in medians.items() if name != "gl"}}
                results["runs"].append(run)
                ratios = " ".join(f"{name} {ratio:.2f}x" for name, ratio in run["gl_over_cpu"].items())
                typer.echo(f"{count} Gaussians {size}x{size}: " + " ".join(f"{k}={v:.1f}ms" for k, v in
                                                                            medians.items()) + f"; GL/CPU {ratios}")
    finally:
        gl.release()
    return results


PLAYER = Path(__file__).resolve().parents[2] / "samples" / "play.py"
SPEECH = Path(__file__).resolve().parents[2] / "samples" / "demo_speech.wav"


def _frames_seconds(head, audio: np.ndarray, rate: int) -> float:
    """Wall seconds of `head.frames` over the whole clip (every frame produced, nothing written)."""
    start = time.perf_counter()
    for _ in head.frames(audio, rate):
        pass
    return time.perf_counter() - start


def run_play_bench(bundle: Path, renderers: list[str], size: int, rounds: int) -> dict:
    """Audio -> pixels and play.py wall seconds per renderer on the sample speech (10 s), alternating rounds."""
    from gaussiantalker.runtime import TalkingHead
    from gaussiantalker.sdk.audio import load_audio

    audio = load_audio(SPEECH, 16000)
    seconds = audio.shape[0] / 16000
    heads = {name: TalkingHead(bundle, resolution=(size, size), composite=False, renderer=name)
             for name in renderers}
    frames_s: dict[str, list[float]] = {name: [] for name in renderers}
    play_s: dict[str, list[float]] = {f"{name} {kind}": [] for name in renderers for kind in ("bare", "composited")}
    try:
        for head in heads.values():  # warm: graphs, GL programs, kernels, first-touch pages
            _frames_seconds(head, audio[:16000], 16000)
        with tempfile.TemporaryDirectory() as tmp:
            for index in range(rounds):
                order = renderers if index % 2 == 0 else renderers[::-1]
                for name in order:
                    frames_s[name].append(_frames_seconds(heads[name], audio, 16000))
                for name in order:
                    for kind in ("bare", "composited"):
                        command = [sys.executable, str(PLAYER), str(bundle), "--audio", str(SPEECH), "-o",
                                   str(Path(tmp) / "out.mp4"), "--renderer", name, "--quiet"]
                        command += ["-r", str(size), "--no-composite"] if kind == "bare" else []
                        start = time.perf_counter()
                        subprocess.run(command, check=True, capture_output=True)
                        play_s[f"{name} {kind}"].append(time.perf_counter() - start)
                typer.echo(f"round {index + 1}/{rounds}: " + " ".join(
                    f"{k}={v[-1]:.2f}s" for k, v in {**frames_s, **play_s}.items()))
    finally:
        for head in heads.values():
            head.close()
    return {"audio_seconds": seconds, "size": size, "rounds": rounds,
            "frames_s": {k: float(np.median(v)) for k, v in frames_s.items()},
            "play_s": {k: float(np.median(v)) for k, v in play_s.items()},
            "frames_rtf": {k: float(np.median(v)) / seconds for k, v in frames_s.items()},
            "play_rtf": {k: float(np.median(v)) / seconds for k, v in play_s.items()}}
