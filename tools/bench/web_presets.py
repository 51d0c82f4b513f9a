"""Bundles for the web (docs/web.md, "Download size and time to the first frame"): each export preset of a speaker,
its bundle's bytes (what a page downloads before anything shows) and, in headless Chromium, the time from asking
for the bundle to the first frame on screen: load (fetch from a local server, read and check, decode the buffers,
create the onnxruntime-web sessions), drive (the voice's first CLIP_S seconds, or the motion, turned into drives in
the browser), first frame.

A download's time depends on the link, not on this machine: the report gives it at DOWNLOAD_MBIT_S, a phone's
ordinary mobile link, beside the measured local figures.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from gaussiantalker.sdk.bundle import Bundle

DOWNLOAD_MBIT_S = (10.0, 50.0)
SIZE = (512, 512)
CLIP_S = 3.0  # the voice's first seconds: a reply's first sentence, translated in the page before its first frame


def _clip(audio: Path, folder: Path) -> Path:
    """The first CLIP_S seconds of `audio` as a 16 kHz 16-bit wav (nothing to decode in the page but the clip)."""
    from gaussiantalker.sdk.audio import load_audio, write_wav

    out = folder / f"{audio.stem}-{CLIP_S:g}s.wav"
    write_wav(out, load_audio(audio, 16000)[: int(CLIP_S * 16000)], 16000)
    return out


def _export(checkpoint: Path, preset: str, out: Path) -> float:
    """`gt-export CHECKPOINT --preset PRESET -o OUT` (not verified: the presets' fidelity is measured elsewhere);
    its seconds."""
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", "from gaussiantalker.cli.export import main; main()",
                           str(checkpoint), "--preset", preset, "-o", str(out)],
                          capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"gt-export {checkpoint.name} --preset {preset} failed: {done.stderr[-2000:]}")
    return time.perf_counter() - start


def _buffer_bytes(bundle: Path) -> dict[str, int]:
    """Stored bytes per buffer group (the name before the first '/') and of the sparse buffers."""
    manifest = Bundle(bundle).manifest
    out: dict[str, int] = {"graphs": sum(g["nbytes"] for g in manifest["graphs"].values())}
    for name, entry in manifest["buffers"].items():
        out[name.split("/")[0]] = out.get(name.split("/")[0], 0) + entry["nbytes"]
        if "sparse" in entry["codec"]:
            out["sparse"] = out.get("sparse", 0) + entry["nbytes"]
    return out


def _first_frame(bundle: Path, audio: Path | None, motion: Path | None, rounds: int, composite: bool = False
                 ) -> dict:
    """Medians over `rounds` fresh pages: seconds to load, to drive and to draw the first frame; the bare head at
    SIZE, or (`composite`) the frame composited into the bundle's reference clip at the clip's size."""
    from tools.browser.web_harness import WebPlayerPage

    runs = []
    for _ in range(rounds):
        with WebPlayerPage() as page:
            start = time.perf_counter()
            info = page.load(bundle, size=None if composite else SIZE, composite=composite)
            loaded = time.perf_counter()
            page.drive(audio=audio, motion=motion)
            driven = time.perf_counter()
            page.render(0)
            drawn = time.perf_counter()
        runs.append({"load": loaded - start, "drive": driven - loaded, "first_frame": drawn - driven,
                     "total": drawn - start, "page_load": info.get("load"), "size": info["size"]})
    return {key: float(np.median([r[key] for r in runs])) for key in ("load", "drive", "first_frame", "total")} | {
        "runs": runs}


def run_web_presets(speakers: list[tuple[str, Path, Path | None, Path | None]], presets: list[str], rounds: int,
                    log=print) -> dict:
    """Per (speaker label, checkpoint, audio, motion) and preset: export, size, time to the first frame."""
    rows = []
    with tempfile.TemporaryDirectory(prefix="gt-web-presets-") as folder:
        for label, checkpoint, audio, motion in speakers:
            audio = _clip(audio, Path(folder)) if audio is not None else None
            for preset in presets:
                bundle = Path(folder) / f"{checkpoint.stem}-{preset}.gtb"
                export_s = _export(checkpoint, preset, bundle)
                size = bundle.stat().st_size
                # A bundle with a reference clip and F is also measured composited (with audio: a motion plays
                # bare; the page has no OpenCV fallback for a clip without F).
                manifest = Bundle(bundle).manifest
                with_clip = audio is not None and "reference" in manifest and "inpaint" in manifest["graphs"]
                for composite in (False, True) if with_clip else (False,):
                    timing = _first_frame(bundle, audio, motion, rounds, composite)
                    row = {"speaker": label, "preset": preset, "composited": composite, "bytes": size,
                           "groups": _buffer_bytes(bundle), "export_seconds": export_s, **timing,
                           "download_seconds": {f"{mbit:g}": size * 8 / (mbit * 1e6) for mbit in DOWNLOAD_MBIT_S}}
                    rows.append(row)
                    log(f"{label} {preset}{' composited' if composite else ''}: {size / 1e6:.2f} MB, load "
                        f"{timing['load']:.2f} s, drive {timing['drive']:.2f} s, first frame "
                        f"{timing['first_frame']:.2f} s")
    return {"rows": rows, "size": list(SIZE), "rounds": rounds, "download_mbit_s": list(DOWNLOAD_MBIT_S),
            "clip_seconds": CLIP_S}


def web_presets_table(result: dict) -> str:
    mbits = result["download_mbit_s"]
    lines = ["| speaker | preset | frame | bundle | of it sparse | download at " + " / ".join(f"{m:g}" for m in mbits)
             + " Mbit/s | load | drive | first frame | to the first frame (local) |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for row in result["rows"]:
        downloads = " / ".join(f"{row['download_seconds'][f'{m:g}']:.1f}" for m in mbits)
        sparse = row["groups"].get("sparse", 0)
        width, height = row["runs"][0].get("size") or result["size"]
        frame = f"{'composited' if row.get('composited') else 'bare'} {width}x{height}"
        lines.append(f"| {row['speaker']} | {row['preset']} | {frame} | {row['bytes'] / 1e6:.2f} MB | "
                     f"{sparse / 1e6:.2f} MB | {downloads} s | {row['load']:.2f} s | {row['drive']:.2f} s | "
                     f"{row['first_frame']:.2f} s | {row['total']:.2f} s |")
    return "\n".join(lines)


__all__ = ["run_web_presets", "web_presets_table"]
