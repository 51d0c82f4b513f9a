"""Speed/accuracy knobs of an export and the named presets built from them (docs/precision.md).

Every trade the exporter offers is a field of `ExportSettings`; a preset is a named `ExportSettings` plus the
runtime defaults stored in the bundle (`TalkingHead` plays a bundle with them unless the app overrides them) and
the bound `gt-export --verify` holds its frames to. The sweep (`gt-bench sweep`) measures every knob alone
and every preset on the same frames; the presets below were chosen from its table.
"""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass, field, fields, replace

import numpy as np

from gaussiantalker.sdk.codecs import CODECS, MAX_CHUNK, MAX_CODEBOOK
from gaussiantalker.sdk.errors import BundleError
from gaussiantalker.sdk.reference_clip import MAX_CLIP_FRAMES, MAX_H264_CRF, ClipCoding, ReferenceClipError
from gaussiantalker.sdk.render_settings import RenderSettings

# The refit's bound, here so that settings are checked without importing torch (exporter/export/refit.py).
MAX_REFIT_STEPS = 100_000


def check_refit_steps(steps: object) -> int:
    """A refit's step count (`ExportSettings.refit_steps`): a whole number in 0..MAX_REFIT_STEPS, else BundleError."""
    if isinstance(steps, bool) or not isinstance(steps, int) or not 0 <= steps <= MAX_REFIT_STEPS:
        raise BundleError(f"refit_steps must be a whole number in 0..{MAX_REFIT_STEPS}, got {steps!r}")
    return steps

# Buffer groups a codec is chosen for, and which bundle buffers (by glob on the buffer name) belong to each.
CODEC_GROUPS: dict[str, tuple[str, ...]] = {
    "gaussians": ("deform/latent_bias", "deform/log_scale", "deform/opacity", "deform/barycentric",
                  "deform/rest_scale", "deform/rotation", "deform/sh_dc"),  # per-Gaussian static attributes
    "sh": ("deform/sh_rest",),  # SH bands 1..3
    "blendshapes": ("deform/latent_weight", "deform/latent_basis", "deform/latent_pose.*"),  # W_pos/rot/color, MLP
    # FLAME bases, rest mesh, skinning; an ARKit speaker's morph targets
    "flame": ("deform/blend_basis", "deform/rest_points", "deform/lbs_weights", "deform/morph_basis"),
    # motion translator weights (fp32 graph), its streaming form and that form's steady one
    "translator": ("translator/*", "translator_stream/*", "translator_stream_steady/*"),
    "inpaint": ("inpaint/*",),  # the inpainting generator's convolutions (docs/compositing.md)
}
# Buffers every frame's geometry hangs on (the rest mesh, the frame guards' reference size, where on its triangle a
# Gaussian sits): a quantised codec gives them at least 16 bits. Measured on the demo speaker, barycentrics at q8
# alone cost far more head-region PSNR than every other per-Gaussian buffer at q8 (docs/precision.md, "Knobs").
KEEP_16_BITS = ("deform/rest_points", "deform/rest_scale", "deform/barycentric", "deform/lbs_weights")
# An ARKit speaker's morph targets get at least 8 bits from a quantised codec: they are sparse with a wide range (a
# chunk of 128 values holds zeros beside 4 cm moves), so 4-bit steps are millimetres. Measured on LAM's sample
# avatar, balanced preset, random strong expressions: head region 41.3 dB with q4/128, 53.7 dB with q8 (docs/import.md).
KEEP_8_BITS = ("deform/morph_basis",)
# Buffers stored sparse (sdk/codecs.py: a bitmask of the nonzero elements, then those values in the buffer's codec)
# when at least SPARSE_MIN_ZEROS of their elements are zero. An ARKit avatar's morph basis is mostly zeros (LAM's
# p2-1: 82%), each blendshape moving one region of the face; FLAME's buffers stay as they are.
SPARSE_BUFFERS = ("deform/morph_basis",)
SPARSE_MIN_ZEROS = 0.5
# Quantised codecs spend 8 bytes of chunk parameters per chunk: below this many values a buffer gets fp16 instead.
QUANT_MIN_VALUES = 4096
# Translator graph precisions (exporter/export/graph_precision.py converts to them).
TRANSLATOR_PRECISIONS = ("fp32", "fp16", "int8")


def parse_codec(spec: str) -> tuple[str, int | None]:
    """A codec knob's value: a codec name, for quantised codecs optionally with its chunk size ("q4/64"), for the
    codebook `vq` with its entries ("vq/1024")."""
    name, _, size_text = str(spec).partition("/")
    allowed = [c for c in CODECS if not CODECS[c].int_only]
    if name not in allowed:
        raise BundleError(f"unknown codec {spec!r} (allowed: {', '.join(allowed)}; quantised ones may name a chunk "
                          f"size, e.g. q4/64, and vq its entries, e.g. vq/1024)")
    if not size_text:
        return name, None
    limit = MAX_CODEBOOK if name == "vq" else MAX_CHUNK
    if not (name.startswith("q") or name == "vq") or not size_text.isdigit() or not 1 <= int(size_text) <= limit:
        raise BundleError(f"codec {spec!r}: only q16/q8/q4 take a chunk size (an integer 1..{MAX_CHUNK}) and vq a "
                          f"number of entries (1..{MAX_CODEBOOK})")
    return name, int(size_text)


def parse_reference(spec: str) -> ClipCoding | None:
    """The reference-clip knob's value: "keep" (the clip stored as the checkpoint holds it: None) or
    "crf:N[,gop:K][,mask-crf:M]": the frames re-encoded with x264 at CRF N, in groups of K pictures (1, intra-only,
    when not given), and the masks coded as H.264 at CRF M in the same groups (kept as stored when not given)."""
    text = str(spec)
    if text == "keep":
        return None
    allowed = (f"allowed: keep, or crf:N[,gop:K][,mask-crf:M] with N and M integers 0..{MAX_H264_CRF} and K an "
               f"integer 1..{MAX_CLIP_FRAMES}, e.g. crf:28,gop:25,mask-crf:24; docs/compositing.md")
    values: dict[str, int] = {}
    for item in text.split(","):
        name, _, value = item.strip().partition(":")
        if name not in ("crf", "gop", "mask-crf") or name in values or not value.isdigit():
            raise BundleError(f"unknown reference clip setting {spec!r} ({allowed})")
        values[name] = int(value)
    if "crf" not in values:
        raise BundleError(f"reference clip setting {spec!r} names no crf ({allowed})")
    try:
        return ClipCoding(values["crf"], values.get("gop", 1), values.get("mask-crf"))
    except ReferenceClipError as exc:
        raise BundleError(f"reference clip setting {spec!r}: {exc} ({allowed})") from None


def group_of(buffer: str) -> str:
    """The codec group of bundle buffer `buffer` ('other' for buffers no codec knob applies to)."""
    return next((group for group, patterns in CODEC_GROUPS.items()
                 if any(fnmatch.fnmatchcase(buffer, p) for p in patterns)), "other")


@dataclass(frozen=True)
class ExportSettings:
    """Export-time knobs: a buffer codec per group, the translator graph's precision, model-size truncations, an
    ARKit rig's midpoint vertices derived (`midpoints`), and how the reference clip is stored (`reference`: "keep"
    or "crf:N[,gop:K][,mask-crf:M]", `parse_reference`)."""

    gaussians: str = "raw"
    sh: str = "raw"
    blendshapes: str = "raw"
    flame: str = "raw"
    translator: str = "raw"
    inpaint: str = "raw"
    translator_precision: str = "fp32"
    sh_degree: int | None = None  # keep SH bands up to this degree (None: all)
    blendshape_rank: int | None = None  # rank of the speaker blendshape matrix (None: full)
    gaussian_budget: float | None = None  # keep this fraction (<= 1) or number (> 1) of Gaussians (None: all)
    # Steps of fitting the budget's kept Gaussians (colours, opacities, scales) to the full speaker's frames, drawn
    # with the alpha cut the bundle's CPU splatter uses (exporter/export/refit.py; 0: kept as they were)
    refit_steps: int = 0
    reference: str = "keep"  # the reference clip: as stored, or re-encoded ("crf:28,gop:25,mask-crf:24")
    # An ARKit rig's edge vertices (a subdivided mesh's) derived from their ends instead of stored, within 10 µm
    # (exporter/export/morph_midpoints.py; a rig whose checkpoint holds its triangles: LAM imports)
    midpoints: bool = False
    # The Gaussians in the Morton order of their positions, so that neighbours share quantisation chunks and runs
    # deflate (exporter/export/spatial_order.py); frames are the same
    spatial_order: bool = False
    # Every buffer stored as a zlib stream where that is smaller (lossless; docs/bundle-format.md, "Buffers")
    deflate: bool = False
    # Codecs of single buffers, (buffer name, codec) pairs: over their group's codec and the 16- and 8-bit floors
    # below (an avatar's own trade: docs/precision.md, "Speakers differ")
    buffer_codecs: tuple[tuple[str, str], ...] = ()

    def __post_init__(self) -> None:
        for group in CODEC_GROUPS:
            try:
                parse_codec(getattr(self, group))
            except BundleError as exc:
                raise BundleError(f"{group}: {exc}") from None
        if self.translator_precision not in TRANSLATOR_PRECISIONS:
            raise BundleError(f"unknown translator precision {self.translator_precision!r} (allowed: "
                              f"{', '.join(TRANSLATOR_PRECISIONS)})")
        if self.sh_degree is not None and not 0 <= self.sh_degree <= 3:
            raise BundleError(f"sh_degree must be 0..3, got {self.sh_degree}")
        if self.blendshape_rank is not None and self.blendshape_rank < 1:
            raise BundleError(f"blendshape_rank must be >= 1, got {self.blendshape_rank}")
        budget = self.gaussian_budget
        if budget is not None and not (budget > 0 and (budget <= 1 or float(budget).is_integer())):
            raise BundleError(f"gaussian_budget must be a fraction in (0, 1] or a whole number of Gaussians, "
                              f"got {budget}")
        check_refit_steps(self.refit_steps)
        if self.refit_steps and budget is None:
            raise BundleError("refit_steps (--refit-steps) fits the Gaussians a budget keeps: give a gaussian_budget "
                              "(--gaussian-budget) too")
        parse_reference(self.reference)
        for pair in self.buffer_codecs:
            if not (isinstance(pair, tuple | list) and len(pair) == 2 and isinstance(pair[0], str)):
                raise BundleError(f"buffer_codecs holds (buffer name, codec) pairs, got {pair!r}")
            try:
                parse_codec(pair[1])
            except BundleError as exc:
                raise BundleError(f"buffer {pair[0]}: {exc}") from None

    @classmethod
    def all_buffers(cls, codec: str) -> ExportSettings:
        """Every group with one codec (what `--codec` sets)."""
        return cls(**dict.fromkeys(CODEC_GROUPS, codec))

    @property
    def lossless(self) -> bool:
        codecs_lossless = all(CODECS[parse_codec(getattr(self, g))[0]].lossless for g in CODEC_GROUPS)
        codecs_lossless = codecs_lossless and all(CODECS[parse_codec(c)[0]].lossless for _, c in self.buffer_codecs)
        return (codecs_lossless and self.translator_precision == "fp32" and self.sh_degree is None
                and self.blendshape_rank is None and self.gaussian_budget is None and self.reference == "keep"
                and not self.midpoints)

    def head_settings(self) -> ExportSettings:
        """These settings with the reference clip stored as it is: what the head's frames depend on (`gt-export
        --verify` composites the runtime's and the torch render into the same decoded clip pictures, so the clip's
        codec is not part of what it proves)."""
        return replace(self, reference="keep")

    def label(self) -> str:
        """fp32, fp16 (every buffer fp16, nothing else changed) or custom."""
        if self.lossless:
            return "fp32"
        if self == ExportSettings.all_buffers("fp16"):
            return "fp16"
        return "custom"

    def codec_for(self, buffer: str, array: np.ndarray) -> tuple[str, int | None]:
        """(codec, chunk or entries) buffer `buffer` is stored with: integer indices `index` (lossless), floats the
        codec `buffer_codecs` names for them, else their group's, but at least 16 bits for `KEEP_16_BITS`, 8 for
        `KEEP_8_BITS` (a codebook there becomes q16 / q8), and fp16 for buffers too small to quantise."""
        if array.dtype in (np.int32, np.int64):  # vertex and triangle indices
            return ("index" if array.size and array.min() >= 0 else "raw"), None
        if array.dtype != np.float32:
            return "raw", None  # graph weights already reduced (fp16 / int8 graphs) are stored as they are
        own = dict(self.buffer_codecs).get(buffer)
        if own is not None:
            codec, chunk = parse_codec(own)
            return ("fp16", None) if codec != "raw" and array.size < QUANT_MIN_VALUES else (codec, chunk)
        group = group_of(buffer)
        codec, chunk = parse_codec(getattr(self, group)) if group in CODEC_GROUPS else ("raw", None)
        if codec == "vq" and (buffer in KEEP_16_BITS or buffer in KEEP_8_BITS):
            codec, chunk = ("q16" if buffer in KEEP_16_BITS else "q8"), None
        if codec.startswith("q"):
            if array.size < QUANT_MIN_VALUES:
                return "fp16", None
            if buffer in KEEP_16_BITS:
                return "q16", chunk
            if buffer in KEEP_8_BITS and codec == "q4":
                return "q8", chunk
        return codec, chunk


def stored_sparse(buffer: str, array: np.ndarray) -> bool:
    """Whether bundle buffer `buffer` is stored sparse: one of SPARSE_BUFFERS, at least SPARSE_MIN_ZEROS zeros."""
    return (buffer in SPARSE_BUFFERS and array.size > 0
            and array.size - np.count_nonzero(array) >= SPARSE_MIN_ZEROS * array.size)


@dataclass(frozen=True)
class Preset:
    """A named bundle recipe: export settings, runtime defaults, and the bound `--verify` holds it to."""

    name: str
    summary: str
    export: ExportSettings
    runtime: RenderSettings = field(default_factory=RenderSettings)
    min_head_psnr_db: float | None = None  # 8-bit PSNR over the head region vs the fp32 speaker's frames
    # A splatter's own runtime defaults where they differ from `runtime` ("cpu": the CPU splatter's), stored in the
    # bundle's `runtime_defaults_by_renderer` so that the runtime picks them for the splatter it draws with.
    runtime_by_renderer: dict[str, RenderSettings] = field(default_factory=dict)
    # A kind of speaker's own export settings where they differ from `export` ("arkit": an ARKit rig's, such as a
    # LAM import), picked by the rig of the speaker exported.
    export_by_rig: dict[str, ExportSettings] = field(default_factory=dict)
    # A kind of speaker's own runtime defaults where they differ, per splatter ("arkit": {"cpu": ...}), over
    # `runtime` ("gl") and `runtime_by_renderer` for that rig's bundles.
    runtime_by_rig: dict[str, dict[str, RenderSettings]] = field(default_factory=dict)

    def runtime_for(self, splatter: str, rig: str = "flame") -> RenderSettings:
        """The runtime defaults of this preset on `splatter` ("gl" or "cpu") for a speaker whose rig is `rig`."""
        own = self.runtime_by_rig.get(rig, {})
        if splatter in own:
            return own[splatter]
        return self.runtime_by_renderer.get(splatter, own.get("gl", self.runtime))

    def stored_runtime(self, rig: str) -> tuple[RenderSettings, dict[str, RenderSettings]]:
        """What a bundle of a `rig` speaker stores: its runtime defaults and each splatter's own where they differ
        (the manifest's `runtime_defaults` and `runtime_defaults_by_renderer`)."""
        base = self.runtime_for("gl", rig)
        by_renderer = {**self.runtime_by_renderer, **self.runtime_by_rig.get(rig, {})}
        return base, {name: settings for name, settings in by_renderer.items() if name != "gl"}

    def export_for(self, rig: str) -> ExportSettings:
        """The export settings of this preset for a speaker whose rig is `rig` ("flame" or "arkit")."""
        return self.export_by_rig.get(rig, self.export)

    def exports(self) -> list[ExportSettings]:
        """Every rig's export settings of this preset, `export` first."""
        return [self.export, *self.export_by_rig.values()]


# Buffer codecs of the reduced presets: per-Gaussian values 8-bit (barycentrics, rest sizes 16-bit), SH bands 4-bit,
# speaker blendshapes and FLAME bases 4-bit in chunks of 64, the translator and the inpainting generator 8-bit (F's
# codecs measured on composited frames: docs/compositing.md, "F's precision"). The chunks are small because the
# opaque demo head needs them: with blendshapes in chunks of 256 and FLAME in chunks of 128 its head region measured
# 42.7 dB (bound 47), with both in chunks of 64 48.3 dB, for 0.18 MB more (docs/precision.md, "Presets").
_REDUCED_CODECS = {"gaussians": "q8", "sh": "q4", "blendshapes": "q4/64", "flame": "q4/64", "translator": "q8",
                   "inpaint": "q8"}
# The reference clip (`reference`; the measured table: docs/compositing.md, "The clip's codec"). Each reduced preset
# stores the clip in groups of 25 pictures (10x fewer bytes than intra pictures of lower quality on the demo clip)
# with H.264 masks, and takes the largest measured x264 CRF whose composited frames stay at least 3 dB above the
# preset's `min_head_psnr_db` (the clip's error at most half the error the bound allows) outside the mask, where the
# frame is the clip itself. On the demo clip, minimum over 150 frames, outside / inside the mask: balanced CRF 16,
# masks 6 (50.2 / 49.1 dB, bound 47: the masks 2.1 dB from it, PNG masks would miss the 5x size goal), mobile 28, 24
# (43.6 / 47.9, 39), compact 33, 30 (39.6 / 47.2, 35), fast 38, 30 (36.2 / 46.8, 29). `quality` keeps the clip.
_CLIP_CRF = {"balanced": "crf:16,gop:25,mask-crf:6", "compact": "crf:33,gop:25,mask-crf:30",
             "fast": "crf:38,gop:25,mask-crf:30", "mobile": "crf:28,gop:25,mask-crf:24"}

# `fast` on the CPU splatter, whose frame is spread over the deformation graph, the sort, the projection and the
# blend rather than llvmpipe's fragments (docs/precision.md, "On both splatters"): the blend shrinks with the pixels
# drawn and the alpha cut, so it draws at most 256x256 pixels (a 512x512 frame at half size; gt-export --verify's
# 256x256 frames keep the 3/4 scale, as on GL) and skips contributions under alpha 0.03, and it sorts by exact keys
# (16-bit ones are slower there). Chosen over the same demo clip at 512x512, alternating with `quality`: caps of
# 288², 272² and 256² with alpha 0.03 measured 2.01x / 39.1 dB, 2.07x / 38.2 dB and 2.16x / 37.2 dB; alpha 0.04
# added 0.03x and cost no head PSNR at 288² (the alpha cut alone: docs/precision.md, "Alpha cut-off").
# `compact` for an ARKit avatar (LAM's p2-1; docs/precision.md, "Speakers differ"): what costs there is each kept
# Gaussian and the morph basis, not a translator or a clip, so its buffers take codings of their own, chosen with
# `gt-bench codings` and then together on the avatar bench's frames: codebooks of 1,024 log-scales and 256
# rotations and colours, rest points at 8 bits in chunks of 64 (in spatial order, which the small chunks need), the
# morph basis in 4-bit chunks of 128, every buffer deflated, and 70% of the Gaussians rather than 65% (what the
# codebooks save buys them back). Measured against `quality` at 512²: 14.3x smaller at 36.2 dB min (the same codings
# at 65% and chunks of 256: 16.4x at 34.5 dB).
_COMPACT_ARKIT_CODECS = (("deform/log_scale", "vq/1024"), ("deform/rotation", "vq/256"), ("deform/sh_dc", "vq/256"),
                         ("deform/rest_points", "q8/64"), ("deform/morph_basis", "q4/128"))
# `fast` and `mobile` for an ARKit avatar (LAM's p2-1, docs/precision.md "Refit"): its Gaussians are translucent
# layers, so a budget alone drops visible ones (60%: 38.5 dB min at 512²) and a smaller draw costs 9 dB more. Their
# budgets' survivors are refit to the full avatar's frames for 400 steps (about 100 s for p2-1 on 2 cores), and
# `fast` draws at full size on the CPU splatter. Chosen on the avatar bench's frames, alternating with `quality`:
# 40% with the alpha cut at 0.03 (fitted with it) 2.19x at 36.0 dB min, at 0.02 1.96x at 36.8, 35% at 0.03 2.30x at
# 34.8 dB; `mobile` at 50% (200 steps) 1.46x at 42.6 dB, where 60% alone measured 1.28x at 38.2. As exported, on the
# avatar bench: `fast` 2.22x at 35.8 dB min, `mobile` 1.52x at 43.8 dB (docs/bench/lam-presets).
# On GL (llvmpipe, whose shaders keep the contract's cut) `fast` draws at full size too: 2.19x at 34.0 dB min against
# 2.39x at 31.3 dB at 3/4 size.
_REFIT_STEPS = 400
_ARKIT_FAST_RUNTIME = {"gl": RenderSettings(render_target="uint8", sort_key_bits=16),
                       "cpu": RenderSettings(render_target="uint8", alpha_min=0.03)}
_COMPACT = ExportSettings(**{**_REDUCED_CODECS, "translator": "q4", "blendshapes": "q4", "flame": "q4",
                             "inpaint": "q4"}, sh_degree=0, blendshape_rank=2, gaussian_budget=0.65, midpoints=True,
                          reference=_CLIP_CRF["compact"])
_MOBILE = ExportSettings(**dict.fromkeys(CODEC_GROUPS, "fp16"), gaussian_budget=0.6, midpoints=True,
                         reference=_CLIP_CRF["mobile"])
# The presets, chosen from measurements on the demo speaker (docs/precision.md has the table and the command).
# `min_head_psnr_db` is what `gt-export --verify` holds a preset to; each sits below what the preset measured, by the
# spread seen between clips and resolutions (`fast` draws at 3/4 size, which costs more at small sizes such as
# gt-export's default 256x256; docs/precision.md, "Presets").
PRESETS: dict[str, Preset] = {
    "quality": Preset("quality", "fp32 everything: parity with the torch speaker (>= 50 dB)", ExportSettings()),
    "balanced": Preset("balanced", "quantised buffers, nothing dropped, the clip in groups of pictures: ~5.5x "
                       "smaller with the demo clip at ~48 dB",
                       ExportSettings(**_REDUCED_CODECS, midpoints=True, reference=_CLIP_CRF["balanced"]),
                       min_head_psnr_db=47.0),
    "compact": Preset("compact", "smallest bundle: 65% of the Gaussians, SH degree 0, rank-2 blendshapes, 4-bit "
                      "translator and inpainting generator, FLAME bases in chunks of 256, the clip in groups of "
                      "pictures: ~14x smaller with the demo clip at ~36 dB on the demo speaker (an ARKit avatar: "
                      "codebooks, spatial order and deflated buffers)",
                      _COMPACT, min_head_psnr_db=35.0,
                      export_by_rig={"arkit": replace(_COMPACT, gaussian_budget=0.7, spatial_order=True, deflate=True,
                                                      buffer_codecs=_COMPACT_ARKIT_CODECS)}),
    "fast": Preset("fast", "fastest frames: 60% of the Gaussians, drawn at 3/4 size into an 8-bit framebuffer, "
                   "16-bit depth-sort keys (on the CPU splatter: at most 256x256 pixels drawn, alpha under 0.03 "
                   "skipped): ~2.4x the frame rate at ~41 dB on GL, ~2.1x at ~37 dB on the CPU splatter (an ARKit "
                   "avatar: 40% of the Gaussians refit to the full avatar's frames, drawn at full size)",
                   ExportSettings(**_REDUCED_CODECS, gaussian_budget=0.6, midpoints=True, reference=_CLIP_CRF["fast"]),
                   RenderSettings(render_scale=0.75, render_target="uint8", sort_key_bits=16), min_head_psnr_db=29.0,
                   runtime_by_renderer={"cpu": RenderSettings(render_scale=0.75, render_target="uint8",
                                                              alpha_min=0.03, max_draw_pixels=256 * 256)},
                   export_by_rig={"arkit": ExportSettings(**_REDUCED_CODECS, gaussian_budget=0.4, midpoints=True,
                                                          refit_steps=_REFIT_STEPS, reference=_CLIP_CRF["fast"])},
                   runtime_by_rig={"arkit": _ARKIT_FAST_RUNTIME}),
    "mobile": Preset("mobile", "for phones and WebGL 2 (docs/porting.md): fp16 buffers, 60% of the Gaussians, an "
                     "RGBA16F framebuffer (GLES 3.0's renderable float, docs/shaders.md), 16-bit depth-sort keys, one "
                     "graph thread: ~1.4x the frame rate at ~48 dB",
                     _MOBILE, RenderSettings(render_target="float16", sort_key_bits=16, graph_threads=1),
                     min_head_psnr_db=39.0,
                     export_by_rig={"arkit": replace(_MOBILE, gaussian_budget=0.5, refit_steps=_REFIT_STEPS)}),
}


def get_preset(name: str) -> Preset:
    """The preset called `name`; BundleError listing the known ones otherwise."""
    try:
        return PRESETS[name]
    except KeyError:
        raise BundleError(f"unknown preset {name!r} (known: {', '.join(PRESETS)})") from None


def settings_with(base: ExportSettings, **overrides) -> ExportSettings:
    """`base` with the given knobs replaced (None values are left as in `base`)."""
    known = {f.name for f in fields(ExportSettings)}
    unknown = set(overrides) - known
    if unknown:
        raise BundleError(f"unknown export settings {sorted(unknown)} (known: {sorted(known)})")
    return replace(base, **{k: v for k, v in overrides.items() if v is not None})


__all__ = ["CODEC_GROUPS", "PRESETS", "SPARSE_BUFFERS", "ExportSettings", "Preset", "get_preset", "group_of",
           "parse_codec", "parse_reference", "settings_with", "stored_sparse"]
