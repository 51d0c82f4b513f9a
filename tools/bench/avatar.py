"""`gt-bench avatar`: an imported avatar (docs/import.md) measured end to end on one machine in one run, a LAM
avatar zip or a GaussianAvatars output directory with the user's FLAME model:

    gt-bench avatar avatar.zip --motion motion.json --demo-checkpoint demo.ckpt --out docs/bench/lam
    gt-bench avatar avatar_dir --flame flame2023.pkl --demo-checkpoint demo.ckpt --out docs/bench/gaussian-avatars

(`--demo-bundle demo.gtb` plays a demo speaker exported before, instead of exporting the checkpoint each run.)

* Costs, in alternating rounds (medians): the import's time (`import_lam`, or `import_gaussian_avatars` with its
  FLAME model's loading), each preset's export time and bundle size (quality is the fp32 bundle), and
  `verify_bundle`'s time on the fp32 bundle at its defaults (25 frames at 256x256) with its minimum 8-bit PSNR and
  its novel views' minimum.
* Quality: each preset's frames against the fp32 bundle's, rendered by the runtime at 512x512 with each bundle's
  own runtime defaults on the splatter a plain `TalkingHead` picks (the speed rounds' one), at frames sampled
  evenly over a motion (`TalkingHead.drives(motion=...)`: an ARKit avatar's
  weights with its pose track, a FLAME avatar's parameters with their own head pose); 8-bit PSNR over the head
  region (the pixels whose fp32 coverage, output="rgba_float" alpha, exceeds 1/255); median and minimum.
* Speed (tools/bench/avatar_speed.py): alternating rounds of playing the avatar's bundle of each preset exported
  through `TalkingHead.frames(motion=...)` and the demo speaker's fp32 bundle (its bare head) through
  `TalkingHead.frames(audio)`, the same number of frames each at 512x512; steady-state ms per frame (the mean
  gap once the first frames are left out: the CPU splatter's loop hands frames over in bursts) per round, medians
  over rounds.

* Variants (`--variant LABEL=PRESET:key=value,...`): a preset's bundle played with other TalkingHead render
  settings than it stores, in the quality and speed measures beside the presets: what each runtime knob trades on
  this avatar.

The motion is a table `head.driver.motion` takes for either rig: ARKit weights [T, 52] or a FLAME table [T, E + 18].
`--presets` (a subset holding quality) and `--verify-frames` trim the costs of a large avatar on a small machine: a
Gaussian budget (compact, fast, mobile) and verify draw with the torch reference rasterizer, whose time grows with
the Gaussians (docs/bench/gaussian-avatars/avatar.md).
"""

from __future__ import annotations

import dataclasses
import datetime
import fractions
import json
import statistics
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from gaussiantalker.exporter.export.bundle_export import export_bundle
from gaussiantalker.exporter.export.presets import PRESETS
from gaussiantalker.exporter.verify.bundle_verify import verify_bundle
from gaussiantalker.runtime.head import TalkingHead
from gaussiantalker.sdk.bundle import Bundle
from gaussiantalker.sdk.files import atomic_write
from gaussiantalker.sdk.flame_motion import FlameMotion
from gaussiantalker.sdk.image import psnr_db
from gaussiantalker.sdk.numerics import ALPHA_MIN, TRANSMITTANCE_MIN
from gaussiantalker.sdk.progress import progress_bar
from gaussiantalker.sdk.rig import ARKIT_BLENDSHAPES, ARKIT_RIG

from .avatar_speed import WARMUP_FRAMES, fps_rounds
from .frames import machine_info

REFERENCE = "quality"  # the fp32 preset: every other preset's frames are compared with its frames
FPS_PRESETS = ("quality", "balanced", "compact", "fast", "mobile")  # the avatar's bundles played in the speed rounds
SIZE = 512  # square frame side of the quality and speed measures
HEAD_COVERAGE = 1.0 / 255.0  # the head region: fp32 coverage above this
# Random ARKit drives (when an ARKit avatar ships no motion and none is given): a new key pose every KEY_FRAMES
# frames, each blendshape active with probability KEY_ACTIVE at a uniform 0..1 weight, linear in between.
RANDOM_SECONDS, KEY_FRAMES, KEY_ACTIVE = 10.0, 15, 0.2


# What a variant may set: TalkingHead's render keywords (docs/embedding.md), each parsed as the type it takes.
VARIANT_KEYS = {"render_scale": float, "render_target": str, "sort_interval": int, "sort_key_bits": int,
                "alpha_min": float, "max_draw_pixels": int, "threads": int, "transmittance_min": float}


@dataclasses.dataclass(frozen=True)
class Variant:
    """A preset's bundle played with other runtime settings than it stores (`settings`: TalkingHead keywords), so
    that the trade each runtime knob makes on this avatar is measured beside the presets."""

    label: str
    preset: str
    settings: dict

    @classmethod
    def parse(cls, text: str) -> Variant:
        """LABEL=PRESET:key=value,key=value (keys: VARIANT_KEYS; max_draw_pixels=0 removes a stored cap)."""
        label, _, rest = text.partition("=")
        preset, _, pairs = rest.partition(":")
        if not label.strip() or preset not in PRESETS:
            raise ValueError(f"{text!r}: give LABEL=PRESET:key=value,... with PRESET one of {', '.join(PRESETS)}")
        settings = {}
        for pair in filter(None, (item.strip() for item in pairs.split(","))):
            key, _, value = pair.partition("=")
            if key not in VARIANT_KEYS or not value:
                raise ValueError(f"{text!r}: {pair!r} is no key=value of {', '.join(VARIANT_KEYS)}")
            try:  # a float may be a fraction: alpha_min=1/255 is the contract's cut
                kind = VARIANT_KEYS[key]
                settings[key] = float(fractions.Fraction(value)) if kind is float else kind(value)
            except (ValueError, ZeroDivisionError):
                raise ValueError(f"{text!r}: {key} takes a {VARIANT_KEYS[key].__name__}, got {value!r}") from None
        return cls(label.strip(), preset, settings)


def check_variants(variants: Sequence[Variant], presets: Sequence[str]) -> None:
    """ValueError unless each variant's preset is among `presets` (the exported ones) and its label is its own."""
    if any(variant.preset not in presets for variant in variants) or \
            len({variant.label for variant in variants} | set(presets)) != len(variants) + len(presets):
        raise ValueError(f"each variant needs its preset among the exported ones ({', '.join(presets)}) and a label "
                         f"no preset or other variant has (variants: {', '.join(v.label for v in variants)})")


def avatar_importer(avatar: Path, flame: Path | None) -> tuple[str, Callable[[], object]]:
    """The import the costs time, by name: a GaussianAvatars directory with its FLAME model (`flame`, loaded by
    every import as `gt-import` does), else a LAM avatar zip."""
    if flame is not None:
        from gaussiantalker.exporter.imports.sources.gaussian_avatars import import_gaussian_avatars

        return "import_gaussian_avatars", lambda: import_gaussian_avatars(avatar, flame)
    from gaussiantalker.exporter.imports.sources.lam import import_lam

    return "import_lam", lambda: import_lam(avatar, progress=False)


def random_motion(frames: int, seed: int = 0) -> np.ndarray:
    """[frames, 52] smooth random ARKit weights (see KEY_FRAMES): what the quality measure drives without a motion."""
    rng = np.random.default_rng(seed)
    keys = 1 + -(-(frames - 1) // KEY_FRAMES)
    shape = (keys + 1, len(ARKIT_BLENDSHAPES))
    values = rng.uniform(0.0, 1.0, shape) * (rng.uniform(size=shape) < KEY_ACTIVE)
    at = np.arange(frames) / KEY_FRAMES
    return np.stack([np.interp(at, np.arange(keys + 1), values[:, k]) for k in range(values.shape[1])], axis=1)


def _table(track) -> np.ndarray:
    """A motion as the table `head.driver.motion` takes back: FLAME [T, E + 18] or ARKit weights [T, 52]."""
    return track.table if isinstance(track, FlameMotion) else track.weights


def bench_motion(head: TalkingHead, motion: Path | None) -> tuple[np.ndarray, str]:
    """The motion the quality and speed measures play (a table at the avatar's fps, see the module docstring) and
    a line saying which."""
    if motion is not None:
        track = head.driver.motion(motion)
        return _table(track), f"{motion.name} ({len(track)} frames at {head.fps} fps)"
    if head.driver.motion_track is not None:
        track = head.driver.motion()
        return _table(track), f"the avatar's own motion track ({len(track)} frames at {head.fps} fps)"
    if head.driver.rig != ARKIT_RIG:
        head.driver.motion()  # a FLAME avatar without a motion: the DriveError saying what to give
    frames = int(round(RANDOM_SECONDS * head.fps))
    return random_motion(frames), (f"random ARKit drives ({frames} frames, seed 0: a key pose every {KEY_FRAMES} "
                                   f"frames, {KEY_ACTIVE:.0%} of the blendshapes at uniform 0..1 weights)")


def sample_indices(count: int, samples: int) -> np.ndarray:
    """`samples` frame indices spread evenly over 0..count-1 (fewer when the motion is shorter)."""
    return np.unique(np.linspace(0, count - 1, min(samples, count)).round().astype(int))


def timed_costs(load: Callable[[], object], folder: Path, rounds: int, presets: Sequence[str] = tuple(PRESETS),
                verify_frames: int = 25) -> tuple[object, dict[str, dict], dict]:
    """`rounds` rounds of importing the avatar (`load`), exporting each of `presets` into `folder` and verifying the
    fp32 bundle on `verify_frames` frames (0: no verify): the speaker, each preset's export (path, seconds per round,
    bytes, Gaussians) and the verify's (seconds per round, frames, resolution, min 8-bit PSNR, novel views' min 8-bit
    PSNR, passed) plus the import's seconds per round."""
    exports = {name: {"path": folder / f"{name}.gtb", "export_s_rounds": []} for name in presets}
    costs: dict = {"import_s_rounds": [], "verify_s_rounds": []}
    steps = rounds * (len(presets) + 1 + (verify_frames > 0))
    with progress_bar(total=steps, desc="import, export, verify", unit="step") as bar:
        for _ in range(rounds):
            bar.set_postfix_str("import")
            start = time.perf_counter()
            speaker = load()
            costs["import_s_rounds"].append(time.perf_counter() - start)
            bar.update()
            for name, export in exports.items():
                bar.set_postfix_str(f"export {name}")
                start = time.perf_counter()
                result = export_bundle(speaker, export["path"], preset=name, progress=False)
                export["export_s_rounds"].append(time.perf_counter() - start)
                export.update(bytes=export["path"].stat().st_size, gaussians=result.gaussians)
                bar.update()
            if not verify_frames:
                continue
            bar.set_postfix_str("verify fp32")
            start = time.perf_counter()
            report = verify_bundle(speaker, exports[REFERENCE]["path"], frames=verify_frames, progress=False)
            costs["verify_s_rounds"].append(time.perf_counter() - start)
            costs.update(frames=len(report["frames"]), resolution=report["resolution"],
                         min_psnr_db=report["min_psnr_db"], views_min_psnr_db=report["views"].get("min_psnr_db"),
                         passed=bool(report["passed"]))
            bar.update()
    for export in exports.values():
        export["export_s"] = statistics.median(export["export_s_rounds"])
    costs["import_s"] = statistics.median(costs["import_s_rounds"])
    costs["verify_s"] = statistics.median(costs["verify_s_rounds"]) if verify_frames else None
    return speaker, exports, costs


def render_at(bundle: Path, motion: np.ndarray, indices: np.ndarray, bar, coverage: bool = False,
              settings: dict | None = None) -> tuple[np.ndarray, np.ndarray | None, dict]:
    """uint8 frames [S, SIZE, SIZE, 3] of `bundle` (its own runtime defaults, or those with `settings` applied, on
    the splatter a plain TalkingHead picks, the one the speed rounds play on) at frames `indices` of `motion` (its
    `motion_drives`), the coverage masks when asked, and the render settings it played with and the splatter."""
    frames, masks = [], []
    wanted = set(indices.tolist())
    with TalkingHead(bundle, resolution=(SIZE, SIZE), composite=False, **(settings or {})) as head:
        for index, drive in enumerate(head.drives(motion=motion)):
            if index not in wanted:
                continue
            frames.append(head.render(drive))
            if coverage:
                masks.append(head.render(drive, output="rgba_float")[..., 3] > HEAD_COVERAGE)
            bar.update()
        settings = {**dataclasses.asdict(head.render_settings), "renderer": head.renderer}
    return np.stack(frames), (np.stack(masks) if coverage else None), settings


def preset_quality(exports: dict[str, dict], motion: np.ndarray, indices: np.ndarray,
                   variants: Sequence[Variant] = ()) -> dict[str, dict]:
    """Per preset, then per variant (by label): head-region 8-bit PSNR of its frames against the fp32 bundle's
    (per frame, median, minimum) and the runtime settings it played with."""
    results = {}
    cases = [(name, export["path"], None) for name, export in exports.items() if name != REFERENCE]
    cases += [(variant.label, exports[variant.preset]["path"], variant.settings) for variant in variants]
    with progress_bar(total=(1 + len(cases)) * len(indices), desc=f"quality at {SIZE}²", unit="frame") as bar:
        reference, heads, settings = render_at(exports[REFERENCE]["path"], motion, indices, bar, coverage=True)
        results[REFERENCE] = {"runtime": settings, "head_pixels_median": int(np.median(heads.sum(axis=(1, 2))))}
        for name, path, overrides in cases:
            bar.set_postfix_str(name)
            frames, _, settings = render_at(path, motion, indices, bar, settings=overrides)
            psnrs = [psnr_db(reference[i][heads[i]], frames[i][heads[i]]) for i in range(len(indices))]
            results[name] = {"runtime": settings, "head_psnr_db": psnrs,
                             "head_psnr_median_db": float(statistics.median(psnrs)), "head_psnr_min_db": min(psnrs)}
    return results


def demo_speaker(checkpoint: Path | None, gaussians: int):
    """The demo speaker's bare head: the checkpoint's, else an untrained one built here (as `gt-bench frames`)."""
    from gaussiantalker.exporter.demo.demo_speaker import make_demo_speaker
    from gaussiantalker.exporter.export.checkpoint import load_checkpoint

    if checkpoint is None:
        speaker, _ = make_demo_speaker(gaussians, train_seconds=0, progress=False)
        return speaker
    speaker = load_checkpoint(checkpoint)
    speaker.reference = speaker.inpaint = None  # the bare head (compositing: tools/bench/composite_cost.py)
    return speaker


def run_avatar_bench(avatar: Path, motion: Path | None, samples: int, fps_seconds: float, rounds: int,
                     demo_checkpoint: Path | None, demo_gaussians: int, out: Path, command: str,
                     note: str | None = None, flame: Path | None = None, presets: Sequence[str] | None = None,
                     verify_frames: int = 25, variants: Sequence[Variant] = (), demo_bundle: Path | None = None
                     ) -> dict:
    """Every measure of the module docstring (`flame` given: `avatar` is a GaussianAvatars directory, else a LAM
    zip; `presets`: a subset holding quality, None: all; `verify_frames` 0: no verify; `variants`: presets' bundles
    played with other runtime settings, in the quality and speed measures too; `demo_bundle`: the demo speaker's
    bundle as exported, instead of exporting `demo_checkpoint` or an untrained one); writes `out`/avatar.md and
    `out`/avatar.json and returns the JSON."""
    presets = tuple(PRESETS) if presets is None else tuple(name for name in PRESETS if name in presets)
    check_variants(variants, presets)
    started = time.perf_counter()
    date = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    machine = machine_info()
    with tempfile.TemporaryDirectory(prefix="gt-bench-avatar-") as tmp:
        folder = Path(tmp)
        importer, load = avatar_importer(avatar, flame)
        speaker, exports, costs = timed_costs(load, folder, rounds, presets, verify_frames)
        with TalkingHead(exports[REFERENCE]["path"], resolution=(SIZE, SIZE), renderer="gl") as head:
            table, motion_line = bench_motion(head, motion)
            fps, rig = head.fps, head.driver.rig
        indices = sample_indices(len(table), samples)
        quality = preset_quality(exports, table, indices, variants)
        if demo_bundle is None:
            demo = demo_speaker(demo_checkpoint, demo_gaussians)
            demo_bundle = folder / "demo.gtb"
            export_bundle(demo, demo_bundle, progress=True)
        played = {name: exports[name]["path"] for name in FPS_PRESETS if name in exports}
        played |= {variant.label: exports[variant.preset]["path"] for variant in variants}
        speed = fps_rounds(played, demo_bundle, table, max(2, int(round(fps_seconds * fps))), rounds, SIZE,
                           {variant.label: variant.settings for variant in variants})
        speed["demo_gaussians"] = Bundle(demo_bundle).manifest["gaussians"]
    reference_bytes = exports[REFERENCE]["bytes"]
    presets = {name: {"export_s": e["export_s"], "export_s_rounds": e["export_s_rounds"],
                      "bundle_mb": e["bytes"] / 1e6, "smaller_than_fp32": reference_bytes / e["bytes"],
                      "gaussians": e["gaussians"], **quality[name]}
               for name, e in exports.items()}
    played_variants = {variant.label: {"preset": variant.preset, "settings": variant.settings, **quality[variant.label]}
                       for variant in variants}
    result = {"command": command, "date": date, "machine": machine, "note": note, "avatar": str(avatar),
              "flame": None if flame is None else str(flame), "importer": importer, "rig": rig,
              "gaussians": speaker.gaussians.count, "import_s": costs.pop("import_s"),
              "import_s_rounds": costs.pop("import_s_rounds"), "verify": costs, "presets": presets,
              "variants": played_variants,
              "quality": {"size": SIZE, "motion": motion_line, "motion_frames": len(table),
                          "frames": [int(i) for i in indices], "head_coverage_above": HEAD_COVERAGE},
              "fps": speed, "run_s": time.perf_counter() - started}
    out.mkdir(parents=True, exist_ok=True)
    with atomic_write(out / "avatar.json", "w") as handle:
        json.dump(result, handle, indent=2)
    with atomic_write(out / "avatar.md", "w") as handle:
        handle.write(format_report(result) + "\n")
    return result


def _runtime_line(settings: dict) -> str:
    """The render settings a bundle played with, briefly."""
    extras = [f"{settings['graph_threads']} graph thread(s)" if settings.get("graph_threads") else "",
              f"alpha cut {settings['alpha_min']:.3g}" if settings.get("alpha_min", ALPHA_MIN) != ALPHA_MIN else "",
              f"T stop {settings['transmittance_min']:.3g}"
              if settings.get("transmittance_min", TRANSMITTANCE_MIN) != TRANSMITTANCE_MIN else "",
              f"at most {settings['max_draw_pixels']:,} px" if settings.get("max_draw_pixels") else "",
              f"{settings['renderer']} splatter" if settings.get("renderer") else ""]
    return (f"scale {settings['render_scale']:g}, {settings['render_target']}, sort keys "
            f"{settings['sort_key_bits']} bits" + "".join(f", {extra}" for extra in extras if extra))


def _rounds(values: list[float], spec: str) -> str:
    """Per-round values, slash-separated."""
    return " / ".join(format(v, spec) for v in values)


def _import_line(result: dict) -> str:
    """The import that was timed (the FLAME model's loading is part of `import_gaussian_avatars`)."""
    importer = result.get("importer", "import_lam")
    return f"`{importer}`" + (" (its FLAME model loaded each time)" if result.get("flame") else "")


def _verify_line(verify: dict) -> str:
    """verify_bundle's time and worst frames, or that it was not run."""
    if verify.get("verify_s") is None:
        return "`verify_bundle`: not run (--verify-frames 0)."
    return (f"`verify_bundle` of the fp32 bundle ({verify['frames']} frames at {verify['resolution'][0]}x"
            f"{verify['resolution'][1]}): {verify['verify_s']:.1f} s ({_rounds(verify['verify_s_rounds'], '.1f')}), "
            f"min 8-bit PSNR {verify['min_psnr_db']:.1f} dB{_views_part(verify)} "
            f"({'passed' if verify['passed'] else 'FAILED'}).")


def _views_part(verify: dict) -> str:
    """The novel views' minimum, when the report has one."""
    views = verify.get("views_min_psnr_db")
    return "" if views is None else f", novel views' min {views:.1f} dB"


def _pose_words(result: dict) -> str:
    """Where the played head's pose comes from: an ARKit avatar's pose track, a FLAME motion's own head pose."""
    return "the avatar's pose track" if result.get("rig", ARKIT_RIG) == ARKIT_RIG else "the motion's own head pose"


def format_report(result: dict) -> str:
    """avatar.md: command, date, machine, then a table per measure."""
    machine = ", ".join(f"{k} {v}" for k, v in result["machine"].items())
    verify, quality, fps = result["verify"], result["quality"], result["fps"]
    lines = ["# gt-bench avatar", "", f"Command: `{result['command']}`", "", f"Date: {result['date']}; the whole "
             f"run took {result['run_s']:.0f} s.", "", f"Machine: {machine}", ""]
    if result.get("note"):
        lines += [f"Note: {result['note']}", ""]
    flame = f" with FLAME model {Path(result['flame']).name}" if result.get("flame") else ""
    lines += [f"Avatar: {Path(result['avatar']).name}{flame}, {result['gaussians']:,} Gaussians.", "",
              "## Import, export and verify", "",
              f"{len(result['import_s_rounds'])} rounds, each importing the avatar, exporting every preset in "
              "this order and verifying the fp32 bundle; medians over rounds (the first export of the run also "
              "pays torch.onnx's start-up).", "",
              f"{_import_line(result)}: {result['import_s']:.2f} s ({_rounds(result['import_s_rounds'], '.2f')}). "
              f"{_verify_line(verify)}", "",
              "| preset | export s (median) | export s per round | bundle MB | × smaller than fp32 | Gaussians |",
              "|---|---|---|---|---|---|"]
    for name, preset in result["presets"].items():
        lines.append(f"| {name} | {preset['export_s']:.2f} | {_rounds(preset['export_s_rounds'], '.1f')} | "
                     f"{preset['bundle_mb']:.2f} | {preset['smaller_than_fp32']:.1f} | {preset['gaussians']:,} |")
    lines += ["", f"## Quality against the fp32 bundle at {quality['size']}x{quality['size']}", "",
              f"{len(quality['frames'])} frames sampled evenly from {quality['motion']}, the head following "
              f"{_pose_words(result)}; each bundle with its own runtime defaults on the splatter that plays it in the "
              "speed rounds below. Head region: the pixels whose fp32 "
              f"coverage exceeds 1/255 (median {result['presets'][REFERENCE]['head_pixels_median']:,} pixels a "
              "frame). 8-bit PSNR.", "",
              "| preset | runtime defaults | head PSNR median dB | head PSNR min dB |", "|---|---|---|---|"]
    for name, preset in result["presets"].items():
        if name == REFERENCE:
            lines.append(f"| {name} | {_runtime_line(preset['runtime'])} | reference | reference |")
        else:
            lines.append(f"| {name} | {_runtime_line(preset['runtime'])} | {preset['head_psnr_median_db']:.1f} | "
                         f"{preset['head_psnr_min_db']:.1f} |")
    if result.get("variants"):
        lines += ["", "Variants: a preset's bundle played with other runtime settings (`--variant`).", "",
                  "| variant | bundle | runtime settings | head PSNR median dB | head PSNR min dB |",
                  "|---|---|---|---|---|"]
        for label, variant in result["variants"].items():
            lines.append(f"| {label} | {variant['preset']} | {_runtime_line(variant['runtime'])} | "
                         f"{variant['head_psnr_median_db']:.1f} | {variant['head_psnr_min_db']:.1f} |")
    lines += ["", f"## Frames per second at {fps['size']}x{fps['size']}", "",
              f"{fps['rounds']} alternating rounds of {fps['frames']} frames each: the avatar's bundles through "
              f"`TalkingHead.frames(motion=...)` (the motion above from its start, "
              f"with {_pose_words(result)}), the demo "
              f"speaker's fp32 bundle ({fps['demo_gaussians']:,} Gaussians, bare head) through "
              "`TalkingHead.frames(audio)` (its translator included). Steady-state ms per frame (the mean gap "
              f"once the first {WARMUP_FRAMES} frames are left out), medians over rounds.", "",
              "| case | ms/frame per round | FPS per round | median ms/frame | median FPS | × demo FPS |",
              "|---|---|---|---|---|---|"]
    for label, case in fps["cases"].items():
        ratio = fps["fps_vs_demo"].get(label)
        lines.append(f"| {label} | {_rounds(case['frame_ms_rounds'], '.1f')} | {_rounds(case['fps_rounds'], '.1f')} | "
                     f"{case['frame_ms']:.1f} | "
                     f"{case['fps']:.1f} | {'1' if ratio is None else f'{ratio:.2f}'} |")
    return "\n".join(lines)
