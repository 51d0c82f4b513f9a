"""`gt-bench compare --baseline DIR`: this SDK and another checkout of it, measured side by side in one run.

These shared machines vary by more than 1.5x from run to run, so a figure is only worth comparing with one taken
in the same run. Each version runs in its own interpreter (`worker.py`, with that version first on the
import path), exports the same speaker checkpoint with its own exporter, and renders the same audio through its
own `TalkingHead`. Rounds alternate the versions (and which goes first), so machine noise falls on both; the
table reports the median over rounds and the ratio baseline / this version. `play.py` is timed the same way, as
a whole command (interpreter start-up, imports, bundle load, GL context, render, encode).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from gaussiantalker.sdk.progress import progress_bar

from .worker import STAGES

PACKAGES = ("sdk", "runtime", "exporter", "shaders")
WORKER = Path(__file__).with_name("worker.py")


def checkout_root(path: Path) -> Path:
    """The folder holding sdk/, runtime/, exporter/ and shaders/ of an SDK checkout (its src/gaussiantalker/, or the
    checkout itself in versions before the src/ layout); ValueError if it is not one."""
    path = path.expanduser().resolve()
    for candidate in (path / "src" / "gaussiantalker", path):
        if all((candidate / name).is_dir() for name in PACKAGES):
            return candidate
    raise ValueError(f"{path} is not a checkout of the SDK (it has no src/gaussiantalker/ holding "
                     f"{', '.join(name + '/' for name in PACKAGES)})")


def checkout_top(root: Path) -> Path:
    """The checkout a version's package folder (`checkout_root`'s answer) belongs to: where samples/ lives."""
    return root.parent.parent if root.name == "gaussiantalker" and root.parent.name == "src" else root


def this_version_root() -> Path:
    """Where this interpreter's `gaussiantalker` packages live (a checkout, or site-packages/gaussiantalker)."""
    import gaussiantalker.sdk

    return Path(gaussiantalker.sdk.__file__).resolve().parent.parent


def _describe(root: Path) -> str:
    """The commit of a checkout (and whether its files differ from it), else its path."""
    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10,
                              check=True).stdout.strip()

    try:
        commit = git("log", "-1", "--format=%h %s")[:72]
        return commit + (" + uncommitted changes" if git("status", "--porcelain", "--untracked-files=no") else "")
    except (OSError, subprocess.SubprocessError):
        return str(root)


@dataclass
class Version:
    """One SDK version under test: its source root and an import path that puts it first."""

    label: str
    root: Path
    shim: Path
    worker: subprocess.Popen | None = None
    description: str = ""

    @classmethod
    def make(cls, label: str, root: Path, tmp: Path) -> Version:
        # A `gaussiantalker` package whose subpackages are links to this version's folders: with the shim first on
        # PYTHONPATH, `import gaussiantalker.runtime` finds this version whatever else is installed.
        shim = tmp / f"path-{label}"
        package = shim / "gaussiantalker"
        package.mkdir(parents=True)
        (package / "__init__.py").write_text("")
        for name in PACKAGES:
            (package / name).symlink_to(root / name, target_is_directory=True)
        return cls(label, root, shim, description=_describe(root))

    def env(self) -> dict[str, str]:
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join([str(self.shim), *filter(None, [env.get("PYTHONPATH")])])
        return env

    def start(self, cwd: Path) -> None:
        runner = "import runpy, sys; runpy.run_path(sys.argv[1], run_name='__main__')"
        self.worker = subprocess.Popen([sys.executable, "-c", runner, str(WORKER)], stdin=subprocess.PIPE,
                                       stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                                       env=self.env(), cwd=cwd)

    def ask(self, **request) -> dict:
        assert self.worker is not None and self.worker.stdin is not None and self.worker.stdout is not None
        self.worker.stdin.write(json.dumps(request) + "\n")
        self.worker.stdin.flush()
        line = self.worker.stdout.readline()
        if not line:
            raise RuntimeError(f"{self.label} ({self.root}): the worker process ended unexpectedly")
        answer = json.loads(line)
        if not answer.pop("ok"):
            raise RuntimeError(f"{self.label} ({self.root}): {request['op']} failed: {answer['error']}")
        return answer

    def stop(self) -> None:
        if self.worker is not None:
            self.worker.stdin.close()
            self.worker.wait(timeout=60)
            self.worker = None


@dataclass
class Comparison:
    """Per-round results of both versions for each (Gaussians, size) case, plus play.py wall times."""

    versions: dict[str, str] = field(default_factory=dict)
    cases: dict[str, dict[str, list[dict]]] = field(default_factory=dict)
    play_s: dict[str, list[float]] = field(default_factory=dict)
    audio_seconds: float = 0.0
    play_audio_seconds: float = 0.0

    def medians(self, case: str, label: str) -> dict[str, float]:
        """Median over rounds of each stage (ms), the pipelined frame time and the sequential sum."""
        rounds = self.cases[case][label]
        out = {stage: statistics.median(r["stages_ms"][stage] for r in rounds) for stage in STAGES}
        out["sequential"] = statistics.median(r["sequential_frame_ms"] for r in rounds)
        out["pipelined"] = statistics.median(r["frame_ms"] for r in rounds)
        return out


def in_turn(items: list, round_index: int) -> list:
    """`items` in round `round_index`'s order: as given in even rounds, reversed in odd ones, so none always goes
    first."""
    return items if round_index % 2 == 0 else items[::-1]


def alternating(labels: list[str], rounds: int):
    """(round, label) pairs with the order reversed every other round: A B, B A, A B, ..."""
    for r in range(rounds):
        for label in in_turn(labels, r):
            yield r, label


def median_ratio(values, baselines) -> float:
    """The median of the rounds' own ratios value / baseline (the two timed back to back in each round): the
    machine's drift between rounds, which each version's own median takes in, cancels."""
    return statistics.median(value / baseline for value, baseline in zip(values, baselines, strict=True))


def compare(baseline: Path, *, gaussians: list[int], sizes: list[int], seconds: float, rounds: int,
            play_seconds: float, warmup: int = 5, progress: bool = True) -> Comparison:
    """Run both versions side by side; see the module docstring."""
    from gaussiantalker.exporter.demo.demo_speaker import make_demo_speaker
    from gaussiantalker.exporter.export.checkpoint import save_checkpoint
    from gaussiantalker.exporter.export.speech import synth_speech
    from gaussiantalker.sdk.audio import write_wav

    result = Comparison(audio_seconds=seconds)
    with tempfile.TemporaryDirectory(prefix="gt-bench-") as tmp_name:
        tmp = Path(tmp_name)
        versions = {"this": Version.make("this", this_version_root(), tmp),
                    "baseline": Version.make("baseline", checkout_root(baseline), tmp)}
        result.versions = {label: f"{v.description} ({v.root})" for label, v in versions.items()}
        audio = tmp / "speech.wav"
        write_wav(audio, synth_speech(seconds, seed=7))
        labels = list(versions)
        steps = len(gaussians) * (len(labels) + len(sizes) * rounds * len(labels))
        bar = progress_bar(total=steps + (rounds * len(labels) if play_seconds > 0 else 0), desc="gt-bench compare",
                   unit="run", disable=not progress)
        try:
            for version in versions.values():
                version.start(tmp)
            for count in gaussians:
                bar.set_postfix_str(f"{count} Gaussians: building and exporting")
                checkpoint = tmp / f"speaker-{count}.ckpt"
                save_checkpoint(make_demo_speaker(count, train_seconds=0, progress=False)[0], checkpoint)
                checkpoints = {"this": checkpoint, "baseline": _without_names(checkpoint)}
                bundles = {label: tmp / f"{label}-{count}.gtb" for label in labels}
                for label, version in versions.items():
                    version.ask(op="export", checkpoint=str(checkpoints[label]), bundle=str(bundles[label]))
                    bar.update()
                for size in sizes:
                    case = f"{count}@{size}"
                    result.cases[case] = {label: [] for label in labels}
                    for _, label in alternating(labels, rounds):
                        bar.set_postfix_str(f"{case}: {label}")
                        result.cases[case][label].append(versions[label].ask(
                            op="frames", bundle=str(bundles[label]), size=size, audio=str(audio), warmup=warmup))
                        bar.update()
            if play_seconds > 0:
                result.play_audio_seconds = play_seconds
                _time_players(versions, tmp, gaussians[0], play_seconds, rounds, result, bar)
        finally:
            bar.close()
            for version in versions.values():
                version.stop()
    return result


def _without_names(checkpoint: Path) -> Path:
    """A copy of a demo checkpoint for the baseline, without the config entries that change no tensor.

    Versions before the named expression fields and the scaled binding reject config keys they do not know; the demo
    speaker's `expression_names` only label its coefficients and its `binding` is the paper's triangle frame (the
    only one those versions have), so dropping them leaves the speaker, its bundle and its frames as they are.
    """
    import torch

    payload = torch.load(checkpoint, weights_only=True)
    if payload["config"].get("binding", "triangle") != "triangle":
        raise ValueError(f"{checkpoint}: compare measures the demo speaker, whose binding is 'triangle'")
    payload["config"].pop("binding", None)
    payload["config"].pop("expression_names", None)
    copy = checkpoint.with_name(checkpoint.stem + "-baseline.ckpt")
    torch.save(payload, copy)
    return copy


def _time_players(versions: dict[str, Version], tmp: Path, count: int, seconds: float, rounds: int,
                  result: Comparison, bar) -> None:
    """Wall time of each version's samples/play.py on the same audio at 512x512, alternating."""
    from gaussiantalker.exporter.export.speech import synth_speech
    from gaussiantalker.sdk.audio import write_wav

    audio = tmp / "play.wav"
    write_wav(audio, synth_speech(seconds, seed=11))
    for _, label in alternating(list(versions), rounds):
        version = versions[label]
        player = _player(version.root)
        if player is None:
            bar.update()
            continue
        bar.set_postfix_str(f"play.py: {label}")
        command = [sys.executable, str(player), str(tmp / f"{label}-{count}.gtb"), "--audio", str(audio),
                   "-o", str(tmp / f"{label}.mp4"), "-r", "512", "--quiet"]
        start = time.perf_counter()
        subprocess.run(command, env=version.env(), cwd=tmp, check=True, capture_output=True)
        result.play_s.setdefault(label, []).append(time.perf_counter() - start)
        bar.update()


def _player(root: Path) -> Path | None:
    """samples/play.py of a checkout (None for an installed package, which does not ship the samples)."""
    player = checkout_top(root) / "samples" / "play.py"
    return player if player.is_file() else None


def format_table(result: Comparison) -> str:
    """Markdown: per-stage medians of both versions and the speed-up baseline / this, per case."""
    lines = [f"this: {result.versions['this']}", f"baseline: {result.versions['baseline']}", "",
             "| case | version | " + " | ".join(STAGES) + " | sequential | pipelined (FPS) |",
             "|---|---|" + "---|" * (len(STAGES) + 2)]
    for case in result.cases:
        count, size = case.split("@")
        name = f"{int(count) // 1000}k @ {size}²"
        this, base = result.medians(case, "this"), result.medians(case, "baseline")
        for label, values in (("baseline", base), ("this", this)):
            cells = [f"{values[s]:.2f}" for s in (*STAGES, "sequential")]
            cells.append(f"{values['pipelined']:.1f} ({1000 / values['pipelined']:.1f})")
            lines.append(f"| {name} | {label} | " + " | ".join(cells) + " |")
        ratios = [f"{base[s] / this[s]:.2f}×" if this[s] > 0 else "–" for s in (*STAGES, "sequential", "pipelined")]
        lines.append(f"| {name} | speed-up | " + " | ".join(ratios) + " |")
    if any(result.play_s.values()):
        lines += ["", f"`play.py` on {result.play_audio_seconds:g} s of audio at 512² (whole command, median of "
                  f"{max(len(v) for v in result.play_s.values())} runs):", ""]
        for label in ("baseline", "this"):
            runs = result.play_s.get(label) or []
            if runs:
                wall = statistics.median(runs)
                lines.append(f"* {label}: {wall:.1f} s, real-time factor {wall / result.play_audio_seconds:.2f}")
    return "\n".join(lines)
