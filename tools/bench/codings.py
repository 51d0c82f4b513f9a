"""`gt-bench codings`: what each coding of a speaker's per-Gaussian buffers would cost, in bytes and in head PSNR,
measured before the bundle format has the coding (docs/precision.md, "Speakers differ"):

    gt-bench codings p2-1.zip --budgets 55,75 --out docs/bench/codings-p2-1

The speaker (a LAM avatar zip, imported without its voice, or a checkpoint) is exported twice: the fp32 `quality`
bundle, the reference, and `compact` (its Gaussian budget, SH degree, midpoints and codecs). Each probe writes a
copy of the compact bundle, every buffer stored raw, whose probed buffer holds what a coding would decode it to,
renders it, and counts the bytes the coding would store:

* `qN` (chunked min/max, sdk/codecs.py) in the Gaussians' order, and `qN, spatial order` with the Gaussians first
  put in the Morton order of their rest points (neighbours in space share a chunk, the order compressed splat
  formats quantise in; the order itself costs nothing where the graph may renumber its Gaussians);
* `vqK`: the bundle format's codebook codec `vq` with K entries (sdk/codecs.py: k-means over the buffer's
  per-Gaussian vectors, float16 entries, each Gaussian's index in ceil(log2 K) bits);
* the compact bundle's own coding of the buffer: the row the others are read against.

Each row also says what zlib (RFC 1950, level 9: what the format already inflates, and browsers too) and lzma (at
its strongest preset) make of the coding's payload: what a general-purpose entropy stage on top would save, without
a model of the values. A last row applies, all at once, each buffer's smallest coding whose own row lost at most
COMBINED_LOSS_DB of head PSNR against compact's: whether the losses add, and the bundle those codings would make.

Frames: FRAMES frames spread over the sample speech (a speaker with a translator), random ARKit drives (an ARKit
speaker, as `gt-bench avatar` draws them) or a FLAME avatar's own motion, at SIZE², each bundle on the renderer a
plain TalkingHead picks; 8-bit PSNR over the head region (the reference's coverage above 1/255), minimum and median.
`--budgets` adds compact exported at other Gaussian budgets: the whole file's bytes and PSNR, the trade a cheaper
coding buys back.
"""

from __future__ import annotations

import lzma
import statistics
import tempfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gaussiantalker.exporter.export.spatial_order import morton_order
from gaussiantalker.sdk.bundle import Bundle, BundleWriter
from gaussiantalker.sdk.codecs import decode_buffer, encode_buffer
from gaussiantalker.sdk.image import psnr_db
from gaussiantalker.sdk.progress import progress_bar

SIZE = 512
FRAMES = 30
CODEBOOK_SIZES = (256, 1024, 4096)
COMBINED_LOSS_DB = 1.5  # the most head PSNR (minimum over the frames) a coding in the combined row lost alone
MORPH_BASIS = "deform/morph_basis"
# Manifest keys BundleWriter writes itself; a rewritten bundle keeps every other one.
_WRITER_KEYS = ("format", "version", "graphs", "buffers", "payload_size")


@dataclass(frozen=True)
class Probe:
    """One coding of one buffer: `make()` gives what it decodes the buffer to, the bytes it would store and its
    payload (made when the probe runs, under the progress bar: a large codebook takes seconds)."""

    buffer: str
    coding: str
    make: Callable[[], tuple[np.ndarray, int, bytes]]


def quantised(values: np.ndarray, codec: str, chunk: int | None, order: np.ndarray | None,
              sparse: bool = False) -> tuple[np.ndarray, int, bytes]:
    """`values` through chunked codec `codec` (in `order` along the last axis where given): (decoded, bytes,
    payload)."""
    array = np.ascontiguousarray(values if order is None else values[..., order], np.float32)
    payload, params = encode_buffer(array, codec, chunk, sparse)
    decoded = decode_buffer(payload, codec, "float32", array.shape, params)
    if order is not None:
        decoded = decoded[..., np.argsort(order)]
    return decoded, len(payload), payload


def codebook(values: np.ndarray, k: int) -> tuple[np.ndarray, int, bytes]:
    """`values` [..., N] (per-Gaussian vectors along the leading axes) through the `vq` codec with a K-vector
    codebook (sdk/codecs.py): (decoded, bytes, payload)."""
    array = np.ascontiguousarray(values, np.float32)
    payload, params = encode_buffer(array, "vq", k)
    return decode_buffer(payload, "vq", "float32", array.shape, params), len(payload), payload


def gaussian_buffers(bundle: Bundle) -> list[str]:
    """The float buffers holding one value (or vector) per Gaussian along their last axis."""
    count = int(bundle.manifest["gaussians"])
    return [name for name, entry in bundle.manifest["buffers"].items()
            if entry["dtype"] == "float32" and entry["shape"] and entry["shape"][-1] == count
            and name.startswith("deform/")]


def as_stored(bundle: Bundle, name: str, values: np.ndarray, codec: str, chunk: int | None = None,
              sparse: bool = False) -> tuple[np.ndarray, int, bytes]:
    """A buffer as the bundle stores it: its values, its stored bytes, and its payload made again with its codec
    (what `lzma` reads; the same codes, so the same size)."""
    payload, _ = encode_buffer(np.ascontiguousarray(values, np.float32), codec, chunk, sparse)
    return values, int(bundle.manifest["buffers"][name]["nbytes"]), payload


def probes(compact: Bundle, order_points: str | None) -> list[Probe]:
    """Every probe of the compact bundle's per-Gaussian buffers (and its morph basis); `order_points`: the buffer
    whose [3, N] points give the spatial order (None: no spatially ordered probes)."""
    order = morton_order(compact.buffer(order_points).T) if order_points else None
    out = []
    for name in gaussian_buffers(compact):
        values = compact.buffer(name)
        codec = compact.manifest["buffers"][name]["codec"]["name"]
        out.append(Probe(name, "as compact stores it", lambda v=values, n=name, c=codec: as_stored(compact, n, v, c)))
        own_bits = int(codec[1:]) if codec.startswith("q") else 32
        for bits in (16, 8, 4):
            if bits < own_bits:
                out.append(Probe(name, f"q{bits}", lambda v=values, b=bits: quantised(v, f"q{b}", None, None)))
        for bits in (16, 8, 4) if order is not None else ():
            if bits <= own_bits:
                out.append(Probe(name, f"q{bits}, spatial order",
                                 lambda v=values, b=bits: quantised(v, f"q{b}", None, order)))
        for k in CODEBOOK_SIZES:
            if k <= values.shape[-1] // 2:
                out.append(Probe(name, f"vq{k}", lambda v=values, k=k: codebook(v, k)))
    if compact.has_buffer(MORPH_BASIS):
        values = compact.buffer(MORPH_BASIS)
        codec = compact.manifest["buffers"][MORPH_BASIS]["codec"]
        out.append(Probe(MORPH_BASIS, "as compact stores it",
                         lambda: as_stored(compact, MORPH_BASIS, values, codec["name"], codec.get("chunk"),
                                           "sparse" in codec)))
        for chunk in (256, 64):
            out.append(Probe(MORPH_BASIS, f"q4/{chunk}, sparse",
                             lambda c=chunk: quantised(values, "q4", c, None, sparse=True)))
    return out


def rewrite(source: Bundle, destination: Path, arrays: dict[str, np.ndarray]) -> Path:
    """A copy of `source` with every buffer stored raw, `arrays` in place of the buffers they name."""
    writer = BundleWriter(metadata={k: v for k, v in source.manifest.items() if k not in _WRITER_KEYS})
    for name in source.manifest["buffers"]:
        writer.add_buffer(name, arrays[name] if name in arrays else source.buffer(name))
    for name in source.graph_names():
        info = source.graph_info(name)
        writer.add_graph(name, source.graph_bytes(name), info["inputs"], info["outputs"], info.get("initializers"))
    writer.write(destination)
    return destination


def frames_of(path: Path, drives: Callable, coverage: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
    """uint8 frames [FRAMES, SIZE, SIZE, 3] of `path` (and its head masks) at the drives `drives(head)` gives."""
    from gaussiantalker.runtime import TalkingHead

    images, masks = [], []
    with TalkingHead(path, resolution=(SIZE, SIZE), composite=False) as head:
        for drive in drives(head):
            images.append(head.render(drive))
            if coverage:
                masks.append(head.render(drive, output="rgba_float")[..., 3] > 1.0 / 255.0)
    return np.stack(images), (np.stack(masks) if coverage else None)


def sampled_drives(head, frames: int | None = None) -> list:
    """`frames` (FRAMES) drives spread over the sample speech (a speaker with a translator), else random ARKit drives
    (an ARKit speaker), else the speaker's own motion (a FLAME avatar; `gt-bench avatar`'s DriveError without one)."""
    from gaussiantalker.sdk.rig import ARKIT_RIG

    from .avatar import bench_motion, random_motion, sample_indices
    from .live_sessions import sample_speech

    if head.driver.has_translator:
        drives = list(head.drives(sample_speech(head.driver.sample_rate), head.driver.sample_rate))
    elif head.driver.rig == ARKIT_RIG:
        drives = list(head.drives(motion=random_motion(150)))
    else:
        drives = list(head.drives(motion=bench_motion(head, None)[0]))
    return [drives[i] for i in sample_indices(len(drives), FRAMES if frames is None else frames)]


def head_psnr(reference: np.ndarray, heads: np.ndarray, frames: np.ndarray) -> tuple[float, float]:
    """(minimum, median) 8-bit PSNR over each frame's head region."""
    values = [psnr_db(reference[i][heads[i]], frames[i][heads[i]]) for i in range(len(frames))]
    return min(values), statistics.median(values)


def run_codings(speaker, budgets: list[float], combined_loss_db: float = COMBINED_LOSS_DB,
                progress: bool = True) -> dict:
    """Export `speaker` as quality and compact, run every probe, the combined row (codings that lost at most
    `combined_loss_db` alone) and every budget; the rows of the report. Graphs the same in several of its exports
    (a translator's) are traced once (`reused_exports`)."""
    from gaussiantalker.exporter.export.bundle_export import export_bundle, rig_of
    from gaussiantalker.exporter.export.onnx_export import reused_exports
    from gaussiantalker.exporter.export.presets import get_preset, settings_with

    with tempfile.TemporaryDirectory(prefix="gt-bench-codings-") as folder, reused_exports():
        folder = Path(folder)
        export_bundle(speaker, folder / "quality.gtb", preset="quality", progress=False)
        export_bundle(speaker, folder / "compact.gtb", preset="compact", progress=False)
        compact = Bundle(folder / "compact.gtb")
        # Every bundle is drawn at the same drives: sampled_drives depends on the speaker only.
        reference, heads = frames_of(folder / "quality.gtb", sampled_drives, coverage=True)
        points = "deform/rest_points" if compact.has_buffer("deform/rest_points") else None
        probe_list = probes(compact, points if points and compact.buffer(points).ndim == 2 else None)
        rows, decoded = [], {}
        compact_psnr = head_psnr(reference, heads, frames_of(folder / "compact.gtb", sampled_drives)[0])
        with progress_bar(total=len(probe_list) + len(budgets) + 1, desc="codings", unit="probe",
                          disable=not progress) as bar:
            for probe in probe_list:
                bar.set_postfix_str(f"{probe.buffer} {probe.coding}")
                values, nbytes, payload = probe.make()
                decoded[probe.buffer, probe.coding] = values
                path = rewrite(compact, folder / "probe.gtb", {probe.buffer: values})
                low, middle = head_psnr(reference, heads, frames_of(path, sampled_drives)[0])
                rows.append({"buffer": probe.buffer, "coding": probe.coding, "bytes": nbytes,
                             "zlib_bytes": len(zlib.compress(payload, 9)),
                             "lzma_bytes": len(lzma.compress(payload, preset=9 | lzma.PRESET_EXTREME)),
                             "head_psnr_min_db": low, "head_psnr_median_db": middle})
                bar.update()
            bar.set_postfix_str("combined")
            chosen = combined_choice(rows, compact_psnr[0], combined_loss_db)
            path = rewrite(compact, folder / "probe.gtb", {row["buffer"]: decoded[row["buffer"], row["coding"]]
                                                             for row in chosen})
            low, middle = head_psnr(reference, heads, frames_of(path, sampled_drives)[0])
            stored = {name: int(entry["nbytes"]) for name, entry in compact.manifest["buffers"].items()}
            combined = {"codings": {row["buffer"]: row["coding"] for row in chosen},
                        "bytes": (folder / "compact.gtb").stat().st_size
                        - sum(stored[row["buffer"]] - row["bytes"] for row in chosen),
                        "head_psnr_min_db": low, "head_psnr_median_db": middle}
            bar.update()
            budget_rows = []
            base = get_preset("compact").export_for(rig_of(speaker))
            for budget in budgets:
                bar.set_postfix_str(f"budget {budget:g}")
                path = folder / f"budget-{budget:g}.gtb"
                result = export_bundle(speaker, path, settings=settings_with(base, gaussian_budget=budget),
                                       progress=False)
                low, middle = head_psnr(reference, heads, frames_of(path, sampled_drives)[0])
                budget_rows.append({"budget": budget, "gaussians": result.gaussians, "bytes": path.stat().st_size,
                                    "head_psnr_min_db": low, "head_psnr_median_db": middle})
                bar.update()
        return {"quality_bytes": (folder / "quality.gtb").stat().st_size,
                "compact_bytes": (folder / "compact.gtb").stat().st_size,
                "compact_budget": get_preset("compact").export_for(rig_of(speaker)).gaussian_budget,
                "compact_gaussians": int(compact.manifest["gaussians"]),
                "compact_head_psnr": compact_psnr, "combined": combined, "combined_loss_db": combined_loss_db,
                "frames": len(reference), "size": SIZE, "probes": rows, "budgets": budget_rows}


def combined_choice(rows: list[dict], compact_min_db: float, loss_db: float = COMBINED_LOSS_DB) -> list[dict]:
    """Per buffer, the row of its smallest coding that lost at most `loss_db` (minimum PSNR) alone."""
    best: dict[str, dict] = {}
    for row in rows:
        if row["head_psnr_min_db"] >= compact_min_db - loss_db and \
                (row["buffer"] not in best or row["bytes"] < best[row["buffer"]]["bytes"]):
            best[row["buffer"]] = row
    return [row for row in best.values() if row["coding"] != "as compact stores it"]


def codings_table(result: dict) -> str:
    """The report's body: what compact is, the probes per buffer, then the budgets."""
    quality, compact = result["quality_bytes"], result["compact_bytes"]
    low, middle = result["compact_head_psnr"]
    lines = [f"`quality` {quality / 1e6:.3f} MB; `compact` {compact / 1e6:.3f} MB ({quality / compact:.1f}x smaller, "
             f"{result['compact_gaussians']:,} Gaussians), head PSNR against `quality` {low:.2f} dB min, "
             f"{middle:.2f} median ({result['frames']} frames at {result['size']}²). 14x smaller would be "
             f"{quality / 14 / 1e6:.3f} MB. Each row changes one buffer of `compact`; \"saves\" is against compact's "
             "own coding of it; the last two byte columns are its payload through zlib (level 9) and lzma (preset 9, "
             "extreme).", "",
             "| buffer | coding | bytes | saves | after zlib | after lzma | head PSNR min | median |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    own = {row["buffer"]: row["bytes"] for row in result["probes"] if row["coding"] == "as compact stores it"}
    for row in result["probes"]:
        saves = own[row["buffer"]] - row["bytes"]
        lines.append(f"| `{row['buffer']}` | {row['coding']} | {row['bytes']:,} | {saves:,} | "
                     f"{row['zlib_bytes']:,} | {row['lzma_bytes']:,} | {row['head_psnr_min_db']:.2f} | "
                     f"{row['head_psnr_median_db']:.2f} |")
    combined = result["combined"]
    names = ", ".join(f"`{name}` {coding}" for name, coding in combined["codings"].items()) or "none"
    lines += ["", f"Combined (each buffer's smallest coding that lost at most {result['combined_loss_db']:g} dB alone: "
              f"{names}): {combined['bytes']:,} bytes, {quality / combined['bytes']:.1f}x smaller than `quality`, head "
              f"PSNR {combined['head_psnr_min_db']:.2f} dB min, {combined['head_psnr_median_db']:.2f} median."]
    if result["budgets"]:
        lines += ["", "Compact at other Gaussian budgets (its own codecs), the whole file:", "",
                  "| budget | Gaussians | bytes | x smaller than quality | head PSNR min | median |",
                  "|---:|---:|---:|---:|---:|---:|"]
        for row in result["budgets"]:
            lines.append(f"| {row['budget']:.0%} | {row['gaussians']:,} | {row['bytes']:,} | "
                         f"{quality / row['bytes']:.1f} | {row['head_psnr_min_db']:.2f} | "
                         f"{row['head_psnr_median_db']:.2f} |")
    return "\n".join(lines) + "\n"


__all__ = ["Probe", "codebook", "codings_table", "probes", "quantised", "rewrite", "run_codings"]
