"""Runtime speed/accuracy knobs of the renderer, shared by the exporter (a preset stores them in the bundle as
its defaults) and the runtime (`TalkingHead` arguments override them). docs/precision.md measures each."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

from . import numerics

# Framebuffer precision: the format the splats are blended into (moderngl texture dtypes).
RENDER_TARGETS = {"float32": "f4", "float16": "f2", "uint8": "f1"}
MIN_RENDER_SCALE = 0.1
MAX_SORT_INTERVAL = 60  # frames; a longer-lived depth order is wrong for any moving head
SORT_KEY_BITS = (32, 16)
MAX_EARLY_STOPS = 8  # segment boundaries; each costs a full-screen pass and a GL flush
# The largest alpha cut-off: a tenth of the way to full opacity; past it a Gaussian's soft edge is cut to its core.
MAX_ALPHA_MIN = 0.1
# The largest transmittance stop: a pixel then stops once 90% of its light is accounted for, within 0.1 of the
# contract's colour (the bound is the stop itself, docs/numerics.md, "Transmittance stop").
MAX_TRANSMITTANCE_MIN = 0.1
# Fields that are experiments, off by default and not in the presets or the knob sweep (docs/precision.md).
EXPERIMENTAL_FIELDS = frozenset({"early_stop"})


def _early_stop(value) -> tuple[float, ...]:
    """`value` as a tuple of strictly increasing fractions in (0, 1), at most MAX_EARLY_STOPS, or ValueError."""
    message = (f"early_stop must be a sequence of at most {MAX_EARLY_STOPS} strictly increasing fractions "
               f"between 0 and 1 (exclusive), e.g. (0.5,); got {value!r}")
    if isinstance(value, str | bytes) or not isinstance(value, tuple | list):
        raise ValueError(message)
    if len(value) > MAX_EARLY_STOPS:
        raise ValueError(message)
    for v in value:
        if isinstance(v, bool) or not isinstance(v, int | float) or not 0.0 < v < 1.0:
            raise ValueError(message)
    if any(b <= a for a, b in zip(value[:-1], value[1:], strict=True)):
        raise ValueError(message)
    return tuple(float(v) for v in value)


@dataclass(frozen=True)
class RenderSettings:
    """`render_scale`: draw at this fraction of the output size, then upscale bilinearly (1: full size);
    `render_target`: framebuffer precision, float32 (the contract's), float16 or uint8;
    `sort_interval`: depth-sort every k-th frame, reusing that order in between (1: every frame);
    `sort_key_bits`: 32 sorts exact float32 depth (the contract's), 16 sorts depth quantised to 65536 levels;
    `graph_threads`: threads each graph runs on (None: the backend's default: one where the CPU splatter draws,
    else every core for onnxruntime);
    `early_stop`: experimental, off by default (docs/numerics.md, "Early stop of saturated pixels"): fractions of
    the depth-sorted Gaussians after which the splatter marks pixels whose transmittance is below the contract's
    TRANSMITTANCE_MIN, so that later Gaussians skip them (() : off; e.g. (0.5,));
    `alpha_min`: the CPU splatter skips each contribution whose alpha is below this, the contract's ALPHA_MIN (1/255)
    by default, up to MAX_ALPHA_MIN: fewer fragments, at the cost of each Gaussian's faintest rim (docs/precision.md,
    "Alpha cut-off"); the GL splatter's shaders keep the contract's;
    `transmittance_min`: the CPU splatter also stops a pixel once a contribution leaves its transmittance T below
    this (the contract's TRANSMITTANCE_MIN, 1e-4, by default, where only the contract's stop applies), up to
    MAX_TRANSMITTANCE_MIN: fewer fragments behind the surface, each channel within this value times the largest
    |colour - background| of the contract's (docs/numerics.md, "Transmittance stop"); the GL splatter draws as
    without it;
    `max_draw_pixels`: draw at most about this many pixels (None: no cap): a larger frame is drawn at the scale that
    fits, the smaller of it and `render_scale`, then upscaled, so a frame's draw costs at most so much at any output
    size while small frames keep their detail."""

    render_scale: float = 1.0
    render_target: str = "float32"
    sort_interval: int = 1
    sort_key_bits: int = 32
    graph_threads: int | None = None
    early_stop: tuple[float, ...] = ()
    alpha_min: float = numerics.ALPHA_MIN
    max_draw_pixels: int | None = None
    transmittance_min: float = numerics.TRANSMITTANCE_MIN

    def __post_init__(self) -> None:
        scale = self.render_scale
        if isinstance(scale, bool) or not isinstance(scale, int | float) or not MIN_RENDER_SCALE <= scale <= 1.0:
            raise ValueError(f"render_scale must be a number in {MIN_RENDER_SCALE}..1, got {scale!r}")
        if self.render_target not in RENDER_TARGETS:
            raise ValueError(f"render_target must be one of {', '.join(RENDER_TARGETS)}, got {self.render_target!r}")
        interval = self.sort_interval
        if isinstance(interval, bool) or not isinstance(interval, int) or not 1 <= interval <= MAX_SORT_INTERVAL:
            raise ValueError(f"sort_interval must be a whole number of frames in 1..{MAX_SORT_INTERVAL}, "
                             f"got {interval!r}")
        if isinstance(self.sort_key_bits, bool) or self.sort_key_bits not in SORT_KEY_BITS:
            raise ValueError(f"sort_key_bits must be 32 or 16, got {self.sort_key_bits!r}")
        threads = self.graph_threads
        if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int) or threads < 1):
            raise ValueError(f"graph_threads must be a whole number >= 1 or None, got {threads!r}")
        object.__setattr__(self, "early_stop", _early_stop(self.early_stop))
        cut = self.alpha_min
        if isinstance(cut, bool) or not isinstance(cut, int | float) or not numerics.ALPHA_MIN <= cut <= MAX_ALPHA_MIN:
            raise ValueError(f"alpha_min must be a number in {numerics.ALPHA_MIN:.6g} (1/255, the contract's) .. "
                             f"{MAX_ALPHA_MIN}, got {cut!r}")
        object.__setattr__(self, "alpha_min", float(cut))
        stop = self.transmittance_min
        if (isinstance(stop, bool) or not isinstance(stop, int | float)
                or not numerics.TRANSMITTANCE_MIN <= stop <= MAX_TRANSMITTANCE_MIN):
            raise ValueError(f"transmittance_min must be a number in {numerics.TRANSMITTANCE_MIN:g} (the contract's) "
                             f".. {MAX_TRANSMITTANCE_MIN}, got {stop!r}")
        object.__setattr__(self, "transmittance_min", float(stop))
        cap = self.max_draw_pixels
        if cap is not None and (isinstance(cap, bool) or not isinstance(cap, int) or cap < 1):
            raise ValueError(f"max_draw_pixels must be a whole number >= 1 or None, got {cap!r}")

    def draw_size(self, width: int, height: int) -> tuple[int, int]:
        """The framebuffer size a (width, height) frame is drawn at: `render_scale` of it, or less where that
        would pass `max_draw_pixels`."""
        scale = self.render_scale
        if self.max_draw_pixels is not None and width * height * scale * scale > self.max_draw_pixels:
            scale = math.sqrt(self.max_draw_pixels / (width * height))
        return max(1, round(width * scale)), max(1, round(height * scale))

    def to_dict(self) -> dict:
        """The settings as a manifest table; `early_stop`, `alpha_min`, `max_draw_pixels` and `transmittance_min`
        only when set, so bundles without them stay readable by runtimes that predate them."""
        data = asdict(self)
        if data["alpha_min"] == numerics.ALPHA_MIN:
            del data["alpha_min"]
        if data["transmittance_min"] == numerics.TRANSMITTANCE_MIN:
            del data["transmittance_min"]
        if data["max_draw_pixels"] is None:
            del data["max_draw_pixels"]
        if not data["early_stop"]:
            del data["early_stop"]
        else:
            data["early_stop"] = list(data["early_stop"])
        return data

    @classmethod
    def from_dict(cls, data: dict) -> RenderSettings:
        """From a manifest's `runtime_defaults` (missing keys keep their defaults); ValueError names a bad one."""
        if not isinstance(data, dict):
            raise ValueError(f"runtime defaults must be a table, got {type(data).__name__}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown runtime defaults {unknown} (known: {sorted(known)})")
        return cls(**data)

    def with_overrides(self, **overrides) -> RenderSettings:
        """These settings with every non-None override applied; `max_draw_pixels=0` removes the pixel cap (None
        there means "not given", as for every override)."""
        given = {k: v for k, v in overrides.items() if v is not None}
        if given.get("max_draw_pixels") == 0:
            given["max_draw_pixels"] = None
        return RenderSettings(**{**self.to_dict(), **given})


# The splatters a bundle may store its own defaults for (manifest `runtime_defaults_by_renderer`): a preset's
# settings can differ between the OpenGL splatter and the CPU splatter, whose costs lie elsewhere (docs/precision.md,
# "On both splatters").
SPLATTERS = ("gl", "cpu")


def stored_defaults(manifest: dict, splatter: str) -> RenderSettings:
    """The render settings a bundle stores for `splatter` ("gl" or "cpu"): its `runtime_defaults_by_renderer` entry
    where it has one, else its `runtime_defaults`; ValueError names a bad table."""
    by_splatter = manifest.get("runtime_defaults_by_renderer", {})
    if not isinstance(by_splatter, dict) or not set(by_splatter) <= set(SPLATTERS):
        raise ValueError(f"runtime_defaults_by_renderer must be a table keyed by {' or '.join(SPLATTERS)}, got "
                         f"{sorted(by_splatter) if isinstance(by_splatter, dict) else type(by_splatter).__name__}")
    if splatter in by_splatter:
        return RenderSettings.from_dict(by_splatter[splatter])
    return RenderSettings.from_dict(manifest.get("runtime_defaults", {}))


__all__ = [
    "EXPERIMENTAL_FIELDS", "MAX_ALPHA_MIN", "MAX_EARLY_STOPS", "MAX_SORT_INTERVAL", "MAX_TRANSMITTANCE_MIN",
    "MIN_RENDER_SCALE", "RENDER_TARGETS", "SORT_KEY_BITS", "SPLATTERS", "RenderSettings", "stored_defaults",
]
