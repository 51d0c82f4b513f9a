"""What the browser player (web/, docs/web.md) shares with this runtime, written out as one generated ES module.

`web/src/generated.js` holds the GLSL ES 3.00 programs exactly as `runtime/splat/programs.py` `program_sources` compiles
them for the "300es" target (shaders/ with the contract's #defines), the ARKit blendshape names, the constants the
player's drive and splat steps use, and the live wire format's (gaussiantalker.serve.wire). The shaders and constants
keep one source each (shaders/, sdk/, runtime/, serve/); the file is their copy for a browser that has no Python,
and `gt-web` and tests/test_web_player.py refuse a copy that no longer matches.

    python -m tools.browser.web_assets          # rewrite web/src/generated.js
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from gaussiantalker.runtime import translate, translate_stream
from gaussiantalker.runtime.onnx_wire import MAX_MESSAGE_DEPTH
from gaussiantalker.runtime.splat.common import FLOATS_PER_SPLAT
from gaussiantalker.runtime.splat.depth_sort import KEY_LEVELS_16
from gaussiantalker.runtime.splat.gl import POINT_BOUND_SAFETY, RUN_COST_IN_SPLATS
from gaussiantalker.runtime.splat.programs import PROGRAMS, QUAD_SLACK_PX, program_sources
from gaussiantalker.sdk import bundle, camera, codecs, config, numerics, reference_clip, zip_reader
from gaussiantalker.sdk.audio import MAX_SAMPLE_MAGNITUDE
from gaussiantalker.sdk.drive import MAX_DRIVE_MAGNITUDE
from gaussiantalker.sdk.flame_motion import MOTION_KEYS, TABLE_POSE_COLUMNS
from gaussiantalker.sdk.json_bounds import MAX_JSON_DEPTH
from gaussiantalker.sdk.motion import DEFAULT_MOTION_FPS, MAX_MOTION_FILE_BYTES, MAX_MOTION_FRAMES
from gaussiantalker.sdk.rig import ARKIT_BLENDSHAPES
from gaussiantalker.serve import wire

# The programs the browser player builds (the early stop's saturation pass is not ported).
WEB_PROGRAMS = ("points", "quads", "background", "upscale")
GENERATED = "src/generated.js"


def web_root() -> Path:
    """The web/ folder of this source tree (the player is not part of the Python wheel)."""
    return Path(__file__).resolve().parents[2] / "web"  # tools/browser/ -> the checkout


def constants() -> dict[str, object]:
    """Every constant the player uses, by the name its Python source gives it."""
    return {
        "WINDOW_FRAMES": translate.WINDOW_FRAMES, "CONTEXT_FRAMES": translate.CONTEXT_FRAMES,
        "CROSSFADE_FRAMES": translate.CROSSFADE_FRAMES, "SILENCE_GATE_DBFS": translate.SILENCE_GATE_DBFS,
        "SILENCE_GATE_RAMP_DB": translate.SILENCE_GATE_RAMP_DB, "MAX_DRIVE_MAGNITUDE": MAX_DRIVE_MAGNITUDE,
        "MAX_SAMPLE_MAGNITUDE": MAX_SAMPLE_MAGNITUDE,
        "DEFAULT_MOTION_FPS": DEFAULT_MOTION_FPS, "MAX_MOTION_FRAMES": MAX_MOTION_FRAMES,
        "MAX_MOTION_FILE_BYTES": MAX_MOTION_FILE_BYTES, "RUN_COST_IN_SPLATS": RUN_COST_IN_SPLATS,
        "POINT_BOUND_SAFETY": POINT_BOUND_SAFETY, "QUAD_SLACK_PX": QUAD_SLACK_PX,
        "EXTENT_SIGMAS": numerics.EXTENT_SIGMAS, "LOW_PASS_PX2": numerics.LOW_PASS_PX2,
        "FOV_CLAMP_MARGIN": numerics.FOV_CLAMP_MARGIN, "DEFAULT_NEAR": numerics.DEFAULT_NEAR,
        # The camera model's conventions and bounds (sdk/camera.py, sdk/numerics.py).
        "CAMERA_KEYS": list(camera.CAMERA_KEYS), "MAX_IMAGE_SIDE": camera.MAX_IMAGE_SIDE,
        "FLOAT32_MAX": camera.FLOAT32_MAX, "MIN_FOCAL_PX": camera.MIN_FOCAL_PX,
        "ROTATION_TOLERANCE": camera.ROTATION_TOLERANCE,
        "KEY_LEVELS_16": KEY_LEVELS_16, "FLOATS_PER_SPLAT": FLOATS_PER_SPLAT, "MAX_MESSAGE_DEPTH": MAX_MESSAGE_DEPTH,
        "MAX_RATIO": zip_reader.MAX_RATIO, "MIN_BUDGET": zip_reader.MIN_BUDGET,
        "MAX_NPZ_BYTES": zip_reader.MAX_NPZ_BYTES, "MAX_NDIM": codecs.MAX_NDIM,
        "FLAME_MOTION_KEYS": [list(pair) for pair in MOTION_KEYS], "TABLE_POSE_COLUMNS": TABLE_POSE_COLUMNS,
        "REST_FRAMES": translate_stream.REST_FRAMES, "FEATURES_PER_FRAME": config.FEATURES_PER_FRAME,
        "LOUDNESS_WINDOW_FRAMES": translate_stream.LOUDNESS_WINDOW_FRAMES,
        "REFRESHED_FRAMES": translate_stream.REFRESHED_FRAMES, "LOUDNESS_RATIO": translate_stream.LOUDNESS_RATIO,
        "CROP_MARGIN_PX": reference_clip.CROP_MARGIN_PX, "CROP_MULTIPLE": reference_clip.CROP_MULTIPLE,
        # The bundle's header and bounds (sdk/bundle.py), and its buffer codecs' tables (sdk/codecs.py).
        "MAGIC": bundle.MAGIC.decode("ascii"), "FORMAT_MAJOR": bundle.FORMAT_MAJOR, "HEADER_SIZE": bundle.HEADER_SIZE,
        "HEADER_LAYOUT": {name: list(span) for name, span in bundle.header_layout().items()},
        "ALIGN": bundle.ALIGN, "MAX_MANIFEST_BYTES": bundle.MAX_MANIFEST_BYTES, "MAX_JSON_DEPTH": MAX_JSON_DEPTH,
        "MAX_GRAPH_BYTES": bundle.MAX_GRAPH_BYTES, "GRAPH_COMPRESSIONS": list(bundle.GRAPH_COMPRESSIONS),
        "DTYPE_TABLE": {name: list(entry) for name, entry in codecs.dtype_table().items()},
        "MAX_CHUNK": codecs.MAX_CHUNK, "MAX_CODEBOOK": codecs.MAX_CODEBOOK, "MAX_ELEMENTS": codecs.MAX_ELEMENTS,
        "INDEX_TYPES": list(codecs.INDEX_TYPES), "QUANT_BITS": list(codecs.QUANT_BITS),
        **wire.js_constants(),
    }


def generated_module() -> str:
    """The text of web/src/generated.js."""
    programs = {name: dict(zip(("vertex", "fragment"), program_sources(name, "300es"), strict=True))
                for name in WEB_PROGRAMS}
    assert set(WEB_PROGRAMS) <= set(PROGRAMS)
    lines = [
        "// Generated by `python -m tools.browser.web_assets` from shaders/, sdk/ and runtime/: do not edit.",
        "// The GLSL ES 3.00 programs are runtime/splat/programs.py program_sources(name, '300es'), #defines included.",
        "",
        f"export const PROGRAMS = {json.dumps(programs, indent=2)};",
        "",
        f"export const ARKIT_BLENDSHAPES = {json.dumps(list(ARKIT_BLENDSHAPES))};",
        "",
        *(f"export const {name} = {json.dumps(value)};" for name, value in constants().items()),
        "",
    ]
    return "\n".join(lines)


def stale_message(root: Path | None = None) -> str | None:
    """None when web/src/generated.js matches this runtime's sources, else what to run."""
    path = (root or web_root()) / GENERATED
    if path.is_file() and path.read_text(encoding="utf-8") == generated_module():
        return None
    return (f"{path} is missing or out of date with shaders/ and the runtime's constants: run "
            "`python -m tools.browser.web_assets`")


def write(root: Path | None = None) -> Path:
    """Rewrite web/src/generated.js; returns its path."""
    path = (root or web_root()) / GENERATED
    path.write_text(generated_module(), encoding="utf-8")
    return path


if __name__ == "__main__":
    print(f"wrote {write(Path(sys.argv[1]) if len(sys.argv) > 1 else None)}")


__all__ = ["GENERATED", "WEB_PROGRAMS", "constants", "generated_module", "stale_message", "web_root", "write"]
