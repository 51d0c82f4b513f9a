"""`gt-bench sweep`: every speed/accuracy knob alone and every preset, measured side by side on the same clip.

For each speaker (the demo speaker and a larger synthetic one), every case's bundle is exported once (cases with
the same export settings share a bundle; runtime knobs play the fp32 bundle with `TalkingHead` arguments). Each
case then gets its own worker process (`worker.py`), so its peak memory is its own, and the rounds
alternate the cases (the order reversed every other round) at each size: machine noise falls on all of them,
and ratios are taken within a round. Each round reloads the bundle (load time) and plays the clip through
`TalkingHead.frames` (frame time and FPS, then per-stage medians). The first round's frames are compared with
the fp32 bundle's frames of the same audio (`quality.py`: head and mouth PSNR/SSIM, translator FLAME error).
With several splatters (`--renderers gl,cpu`), every case is measured with each in the same rounds, and each
splatter's ratios and quality are taken against `quality` drawn by that splatter: a preset's trade on the renderer
a user's machine picks.
"""

from __future__ import annotations

import json
import statistics
import tempfile
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from gaussiantalker.exporter.export.presets import PRESETS, ExportSettings
from gaussiantalker.sdk.progress import progress_bar
from gaussiantalker.sdk.render_settings import RenderSettings

from .bare_head import without_clip
from .compare import Version, alternating, this_version_root
from .quality import clip_quality, reference_clip
from .worker import STAGES

REFERENCE = "quality"  # the fp32 bundle every case is compared with (the `quality` preset)
# TalkingHead's splatters by their `renderer` name, as the report names them.
RENDERER_NAMES = {"gl": "OpenGL splatter", "cpu": "CPU splatter"}


@dataclass(frozen=True)
class SweepCase:
    """One measured setting: a knob alone (`group` names it) or a preset, as export settings plus runtime
    arguments of `TalkingHead`."""

    name: str
    group: str
    export: ExportSettings = field(default_factory=ExportSettings)
    runtime: dict = field(default_factory=dict)
    preset: str | None = None
    scene: str | None = None  # a scene file the bundle is specialised for (docs/scene.md)

    @property
    def bundle_key(self) -> str:
        """Cases with the same key play the same bundle: the same export settings, stored runtime defaults and
        scene."""
        defaults = PRESETS[self.preset].runtime if self.preset else RenderSettings()
        return json.dumps([asdict(self.export), defaults.to_dict(), self.scene], sort_keys=True)


def sweep_cases() -> list[SweepCase]:
    """The reference, every knob setting alone (docs/precision.md lists the knobs), then the other presets."""
    def knob(name: str, group: str, **export) -> SweepCase:
        return SweepCase(name, group, ExportSettings(**export))

    def runtime(name: str, group: str, **settings) -> SweepCase:
        return SweepCase(name, group, runtime=settings)

    cases = [SweepCase(REFERENCE, "preset", PRESETS[REFERENCE].export, preset=REFERENCE)]
    for group in ("gaussians", "sh", "blendshapes", "flame", "translator"):
        codecs = {"gaussians": ("fp16", "q16", "q8", "vq/256"), "sh": ("fp16", "q8", "q4"),
                  "blendshapes": ("fp16", "q8", "q4"), "flame": ("fp16", "q8", "q4/128"),
                  "translator": ("fp16", "q8", "q4")}[group]
        cases += [knob(f"{group} {codec}", f"{group} codec", **{group: codec}) for codec in codecs]
    cases += [knob(f"translator graph {p}", "translator precision", translator_precision=p) for p in ("fp16", "int8")]
    cases += [knob(f"SH degree {d}", "SH degree", sh_degree=d) for d in (2, 1, 0)]
    cases += [knob(f"blendshape rank {r}", "blendshape rank", blendshape_rank=r) for r in (6, 4, 2)]
    cases += [knob(f"budget {round(100 * b)}%", "Gaussian budget", gaussian_budget=b) for b in (0.7, 0.5)]
    cases += [knob("budget 50% refit", "refit", gaussian_budget=0.5, refit_steps=400)]  # beside the budget alone
    cases += [knob("midpoints derived", "midpoints", midpoints=True)]  # an ARKit rig's only: FLAME speakers as stored
    # a buffer every rig stores (an unknown name is an export error: bundle_export.check_buffer_codecs)
    cases += [knob("log-scales vq/1024", "one buffer's codec", buffer_codecs=(("deform/log_scale", "vq/1024"),))]
    cases += [knob("spatial order", "spatial order", spatial_order=True)]
    cases += [knob("deflated buffers", "deflate", deflate=True)]
    cases += [runtime(f"framebuffer {t}", "framebuffer", render_target=t) for t in ("float16", "uint8")]
    cases += [runtime(f"render scale {s}", "render scale", render_scale=s) for s in (0.75, 0.5)]
    cases += [runtime(f"sort every {k} frames", "sort interval", sort_interval=k) for k in (2, 4)]
    cases += [runtime("sort keys 16-bit", "sort key bits", sort_key_bits=16)]
    cases += [runtime(f"alpha cut {a}", "alpha cut", alpha_min=a) for a in (0.02, 0.05)]
    cases += [runtime(f"T stop {n}/255", "transmittance stop", transmittance_min=n / 255) for n in (1, 4)]
    cases += [runtime("draw at most 256²", "pixel cap", max_draw_pixels=256 * 256)]
    cases += [runtime("graph threads 1", "graph threads", threads=1)]
    cases += [SweepCase(name, "preset", preset.export, preset=name) for name, preset in PRESETS.items()
              if name != REFERENCE]
    return cases


def scene_cases(scene: str, presets: tuple[str, ...] = tuple(PRESETS)) -> list[SweepCase]:
    """Each preset plain and specialised for the scene file `scene`, side by side (the reference first)."""
    cases = []
    for name in presets:
        preset = PRESETS[name]
        cases += [SweepCase(name, "preset", preset.export, preset=name),
                  SweepCase(f"{name} + scene", "scene", preset.export, preset=name, scene=scene)]
    return cases


def select_cases(cases: list[SweepCase], only: str | None) -> list[SweepCase]:
    """The cases whose name or group contains one of the comma-separated words of `only` (the reference always)."""
    if not only:
        return cases
    words = [w.strip().lower() for w in only.split(",") if w.strip()]
    chosen = [c for c in cases if c.name == REFERENCE or any(w in c.name.lower() or w in c.group.lower()
                                                              for w in words)]
    if len(chosen) == 1:
        raise ValueError(f"no sweep case matches {only!r} (cases: {', '.join(c.name for c in cases)})")
    return chosen


@dataclass
class SpeakerSweep:
    """Everything measured for one speaker: per case, its bundle, timings per size and round, and quality."""

    speaker: str
    gaussians: int
    cases: dict[str, dict] = field(default_factory=dict)


def _export_bundles(speaker, cases: list[SweepCase], tmp: Path, bar, whole_files: bool = False) -> dict[str, dict]:
    """Export each distinct bundle of the bare head once: key -> {path, bytes, gaussians, export_s}; with
    `whole_files` (a speaker with its reference clip and inpainter) each preset's whole file too, weighed and
    deleted ("whole_bytes"). Graphs the same in several bundles are traced once (`reused_exports`), so export_s
    is a bundle's own export only for the first to need each graph."""
    from gaussiantalker.exporter.export.onnx_export import reused_exports

    bundles: dict[str, dict] = {}
    with reused_exports():
        for case in cases:
            if case.bundle_key not in bundles:
                bundles[case.bundle_key] = _export_case(speaker, case, tmp / f"bundle-{len(bundles)}.gtb", bar,
                                                        whole_files)
    return bundles


def _export_case(speaker, case: SweepCase, path: Path, bar, whole_files: bool) -> dict:
    """One case's bare-head bundle at `path`, and its whole file's size where asked (`_export_bundles`)."""
    from gaussiantalker.exporter.export.bundle_export import export_bundle
    from gaussiantalker.sdk.scene import load_scene

    bar.set_postfix_str(f"export {case.name}")
    start = time.perf_counter()
    scene = None if case.scene is None else load_scene(case.scene)
    with without_clip(speaker) as bare:
        if case.preset:
            result = export_bundle(bare, path, preset=case.preset, progress=False, scene=scene)
        else:
            result = export_bundle(bare, path, settings=case.export, progress=False, scene=scene)
    exported = {"path": str(path), "bytes": path.stat().st_size, "gaussians": result.gaussians,
                "export_s": time.perf_counter() - start}
    if whole_files and case.preset and case.scene is None:
        bar.set_postfix_str(f"export {case.name}, whole file")
        whole = path.with_name("whole.gtb")
        export_bundle(speaker, whole, preset=case.preset, progress=False)
        exported["whole_bytes"] = whole.stat().st_size
        whole.unlink()
    bar.update()
    return exported


def sweep_speaker(name: str, speaker, cases: list[SweepCase], *, sizes: list[int], seconds: float, rounds: int,
                  warmup: int = 5, progress: bool = True, renderer: str = "gl") -> SpeakerSweep:
    """Measure every case on one speaker with one splatter (see the module docstring)."""
    return sweep_speaker_renderers(name, speaker, cases, sizes=sizes, seconds=seconds, rounds=rounds, warmup=warmup,
                                   progress=progress, renderers=(renderer,))[0]


def sweep_name(speaker: str, renderer: str, renderers: tuple[str, ...]) -> str:
    """A speaker's sweep as the report names it: with its splatter where the run measured more than one."""
    return speaker if len(renderers) == 1 else f"{speaker}, {RENDERER_NAMES.get(renderer, renderer)}"


def sweep_speaker_renderers(name: str, speaker, cases: list[SweepCase], *, sizes: list[int], seconds: float,
                            rounds: int, renderers: tuple[str, ...] = ("gl",), warmup: int = 5,
                            progress: bool = True, whole_files: bool = False) -> list[SpeakerSweep]:
    """Measure every case on one speaker with each splatter in `renderers` (TalkingHead's `renderer`), every
    (case, splatter) pair in its own worker and all of them alternating in each round; one SpeakerSweep per
    splatter, its ratios and quality against `quality` drawn by the same splatter (module docstring). The cases
    play the bare head; with `whole_files` (a speaker with its reference clip) the presets' whole files are weighed
    too."""
    from gaussiantalker.exporter.export.speech import synth_speech
    from gaussiantalker.runtime.head import TalkingHead
    from gaussiantalker.sdk.audio import write_wav

    results = {r: SpeakerSweep(sweep_name(name, r, renderers), speaker.gaussians.count) for r in renderers}
    labels = [c.name for c in cases]
    runs_of = [(label, r) for r in renderers for label in labels]  # what a round alternates
    by_name = {c.name: c for c in cases}
    distinct = len({c.bundle_key for c in cases})
    bar = progress_bar(total=distinct + len(sizes) * rounds * len(runs_of) + len(runs_of), unit="run",
                       disable=not progress, desc=f"gt-bench sweep {name}")
    with tempfile.TemporaryDirectory(prefix="gt-sweep-") as tmp_name:
        tmp = Path(tmp_name)
        audio = tmp / "speech.wav"
        samples = synth_speech(seconds, seed=7)
        write_wav(audio, samples)
        bundles = _export_bundles(speaker, cases, tmp, bar, whole_files)
        # One package path for every worker: numba keys its kernel cache by the source file's path, so the first
        # worker on the CPU splatter compiles its kernels and the others load them (one shim each compiled each).
        shared = Version.make("this", this_version_root(), tmp)
        workers = {run: replace(shared, label=f"case{i}") for i, run in enumerate(runs_of)}
        for renderer, result in results.items():
            for label in labels:
                bundle = bundles[by_name[label].bundle_key]
                result.cases[label] = {"group": by_name[label].group, "preset": by_name[label].preset,
                                       "scene": by_name[label].scene, "renderer": renderer,
                                       "export": asdict(by_name[label].export), "runtime": by_name[label].runtime,
                                       "bundle_bytes": bundle["bytes"], "whole_bytes": bundle.get("whole_bytes"),
                                       "gaussians": bundle["gaussians"],
                                       "export_s": bundle["export_s"], "sizes": {}}
        try:
            for worker in workers.values():
                worker.start(tmp)
            for size in sizes:
                runs: dict[tuple[str, str], list[dict]] = {run: [] for run in runs_of}
                for round_index, (label, renderer) in alternating(runs_of, rounds):
                    bar.set_postfix_str(f"{size}² round {round_index + 1}: {label} ({renderer})")
                    save = str(_frames_path(tmp, runs_of, (label, renderer), size)) if round_index == 0 else None
                    settings = {**by_name[label].runtime, "renderer": renderer}
                    runs[label, renderer].append(workers[label, renderer].ask(
                        op="frames", bundle=bundles[by_name[label].bundle_key]["path"], size=size, audio=str(audio),
                        warmup=warmup, settings=settings, save=save, reopen=True))
                    bar.update()
                for worker in workers.values():
                    worker.ask(op="release")
                for renderer, result in results.items():
                    _record_size(result, {label: runs[label, renderer] for label in labels}, size)
                bar.set_postfix_str(f"{size}²: quality")
                flames = {}
                for index, label in enumerate(labels):  # each case's translator output, in its own process
                    translated = tmp / f"flame-{index}.npz"
                    if not translated.exists():
                        workers[label, renderers[0]].ask(op="translate", bundle=bundles[by_name[label].bundle_key]
                                                         ["path"], audio=str(audio), save=str(translated))
                    flames[label] = np.load(translated)
                reference_flame = flames[REFERENCE]
                for renderer, result in results.items():
                    with TalkingHead(bundles[by_name[REFERENCE].bundle_key]["path"], resolution=(size, size),
                                     renderer=renderer) as head:
                        reference = reference_clip(head, samples,
                                                   np.load(_frames_path(tmp, runs_of, (REFERENCE, renderer), size)),
                                                   reference_flame["expression"], reference_flame["jaw"])
                    for label in labels:
                        flame = flames[label]
                        frames = np.load(_frames_path(tmp, runs_of, (label, renderer), size))
                        result.cases[label]["sizes"][str(size)]["quality"] = clip_quality(
                            reference, frames, flame["expression"], flame["jaw"])
            for (label, renderer), worker in workers.items():
                results[renderer].cases[label]["peak_rss_mb"] = worker.ask(op="memory")["peak_rss_mb"]
                bar.update()
        finally:
            bar.close()
            for worker in workers.values():
                worker.stop()
    return list(results.values())


def _frames_path(tmp: Path, runs_of: list[tuple[str, str]], run: tuple[str, str], size: int) -> Path:
    """Where the first round of `run` (case, splatter) saves its frames at `size`."""
    return tmp / f"frames-{runs_of.index(run)}-{size}.npy"


def _record_size(result: SpeakerSweep, runs: dict[str, list[dict]], size: int) -> None:
    """Medians over rounds per case, and each case's frame-rate ratio to the reference within each round."""
    reference = runs[REFERENCE]
    for label, rounds in runs.items():
        loads = [r["load_s"] for r in rounds if r.get("load_s") is not None]
        ratios = [ref["frame_ms"] / r["frame_ms"] for ref, r in zip(reference, rounds, strict=True)]
        result.cases[label]["sizes"][str(size)] = {
            "frame_ms": statistics.median(r["frame_ms"] for r in rounds),
            "fps": statistics.median(r["fps"] for r in rounds),
            "fps_vs_reference": statistics.median(ratios),
            "fps_vs_reference_rounds": ratios,
            "load_s": statistics.median(loads) if loads else None,
            "stages_ms": {stage: statistics.median(r["stages_ms"][stage] for r in rounds) for stage in STAGES},
            "rounds": len(rounds),
        }


__all__ = ["REFERENCE", "RENDERER_NAMES", "SpeakerSweep", "SweepCase", "scene_cases", "select_cases", "sweep_cases",
           "sweep_name", "sweep_speaker", "sweep_speaker_renderers"]
