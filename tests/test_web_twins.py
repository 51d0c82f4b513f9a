"""The browser player's twins of Python arithmetic that stays written in both languages (docs/web.md, "One
source"), run by node on seeded cases against their Python reference:

* the translator's window plan, silence gate and cross-fades (web/src/drive.js `translateAudio` against
  runtime/translate.py `translate_audio`), over window settings, fractional frame lengths and levels on the gate's
  ramp, through a stand-in translator whose outputs copy samples of its window (no arithmetic of its own, so any
  difference is the windowing's);
* the camera model's checks (web/src/camera.js `Camera.fromDict` against sdk/camera.py `Camera.from_dict`), over
  valid cameras and each field set to values a manifest could hold;
* the size a frame is drawn at (web/src/camera.js `drawnSize` against `RenderSettings.draw_size`), over render
  scales and pixel caps.

Needs node (.ci/browser's npm brings it in CI, where this test fails without it)."""

from __future__ import annotations

import base64
import json
import math
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from ci_tools import BROWSER_INSTALL, need

from gaussiantalker.runtime.translate import SILENCE_GATE_DBFS, SILENCE_GATE_RAMP_DB, translate_audio
from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.errors import CameraError
from gaussiantalker.sdk.render_settings import RenderSettings

ROOT = Path(__file__).resolve().parents[1]
CASES = {"ci": 200, "heavy": 2000}
NODE_TIMEOUT_S = 300
# The stand-in translator's outputs: expression [frames, 3], jaw [frames, 3], each a copy of one sample of the window
# (picked by integer arithmetic in both languages) or a count, so the rows differ only where the windowing does.
EXPRESSION_WIDTH = 3

SCRIPT = """
import fs from 'node:fs';
import { translateAudio } from %(drive_js)s;
import { Camera, CameraError, drawnSize } from %(camera_js)s;
const { windows, cameras, draws } = JSON.parse(fs.readFileSync(%(cases)s, 'utf8'));
const floats = (text) => new Float32Array(new Uint8Array(Buffer.from(text, 'base64')).buffer);
const fake = (spf) => async (chunk) => {
  const frames = Math.round(chunk.length / spf);
  const expression = new Float32Array(frames * 3);
  const jaw = new Float32Array(frames * 3);
  for (let f = 0; f < frames; f++) {
    expression.set([chunk[Math.min(f * 7, chunk.length - 1)], chunk[(f * 13 + 5) %% chunk.length], f], f * 3);
    jaw.set([chunk[0], chunk[chunk.length - 1], frames], f * 3);
  }
  return { expression: { data: expression, dims: [1, frames, 3] }, jaw_pose: { data: jaw, dims: [1, frames, 3] } };
};
const rows = [];
for (const c of windows) {
  const result = await translateAudio(fake(c.spf), floats(c.audio), c.spf, { gateDbfs: c.gate,
    windowFrames: c.window, contextFrames: c.context, crossfadeFrames: c.crossfade });
  rows.push(Buffer.from(result.rows.buffer).toString('base64'));
}
const verdicts = cameras.map((data) => {
  try {
    Camera.fromDict(data);
    return 'loaded';
  } catch (error) {
    return error instanceof CameraError ? 'refused' : `crashed: ${error}`;
  }
});
const sizes = draws.map((d) => drawnSize(d, d.width, d.height));
console.log(JSON.stringify({ rows, verdicts, sizes }));
"""


def _fake_translator(samples_per_frame: float):
    """The stand-in translator of the module docstring, in Python."""
    def run(chunk: np.ndarray) -> dict:
        frames = round(chunk.shape[0] / samples_per_frame)
        index = np.arange(frames)
        expression = np.stack([chunk[np.minimum(index * 7, chunk.shape[0] - 1)],
                               chunk[(index * 13 + 5) % chunk.shape[0]], index.astype(np.float32)], axis=-1)
        jaw = np.broadcast_to(np.array([chunk[0], chunk[-1], frames], np.float32), (frames, 3))
        return {"expression": expression[None].astype(np.float32), "jaw_pose": jaw[None].astype(np.float32)}
    return run


def _window_cases(count: int, seed: int) -> list[dict]:
    """Audio of 1-120 frames in pieces at levels around the gate's ramp, with random window settings."""
    rng = np.random.default_rng(seed)
    cases = []
    for _ in range(count):
        spf = float(rng.choice([640.0, 1600.0 / 3.0, 320.0, 441.0, 16000.0 / 24.0]))
        frames = int(rng.integers(1, 121))
        length = max(1, int(frames * spf - rng.integers(0, int(spf))))
        audio = rng.standard_normal(length)
        for start in range(0, length, int(spf * rng.integers(3, 30))):  # each piece at its own level
            level_db = rng.uniform(SILENCE_GATE_DBFS - SILENCE_GATE_RAMP_DB - 3, SILENCE_GATE_DBFS + 3)
            audio[start:] *= 10 ** (rng.choice([level_db, -20.0, -200.0]) / 20)
        window = int(rng.integers(1, 41))
        context = int(rng.integers(0, 11))
        crossfade = int(rng.integers(0, min(2 * context, window) + 1))
        cases.append({"audio": audio.astype(np.float32), "spf": spf, "window": window, "context": context,
                      "crossfade": crossfade, "gate": rng.choice([None, SILENCE_GATE_DBFS, -20.0])})
    return cases


def _camera_cases(count: int, seed: int) -> list[object]:
    """Valid camera descriptions, and each with one field set to what a manifest could hold instead."""
    rng = np.random.default_rng(seed)
    strange = [0, -1, 1.5, 16384, 16385, 1e-39, 1e-45, 3.5e38, 3.4e38, "512", True, False, None, [], [1, 2, 3],
               {}, 1e308, -1e308, 0.0, 2, 1e5]
    cases: list[object] = [None, [], "camera", {}]
    for _ in range(count):
        camera = Camera.looking_at(rng.normal(size=3) * 2 + [0, 0, -3], [0, 0, 0], [0, -1, 0],
                                   int(rng.integers(1, 2048)), int(rng.integers(1, 2048)),
                                   float(rng.uniform(1, 179))).to_dict()
        roll = rng.integers(0, 6)
        if roll == 0:
            pass
        elif roll == 1:
            camera[str(rng.choice(list(camera)))] = strange[rng.integers(len(strange))]
        elif roll == 2:
            del camera[str(rng.choice(list(camera)))]
        elif roll == 3:  # R nudged by a scale around the rotation tolerance, or mirrored
            camera["R"] = (np.asarray(camera["R"]) * rng.choice([1 + 4e-6, 1 + 2e-5, -1.0, 1.0])).tolist()
        elif roll == 4:  # one entry of R or t replaced
            name = str(rng.choice(["R", "t"]))
            flat = np.asarray(camera[name], dtype=object).reshape(-1)
            flat[rng.integers(flat.size)] = strange[rng.integers(len(strange))]
            camera[name] = flat.reshape(np.shape(camera[name])).tolist()
        else:  # R or t of another shape
            camera[str(rng.choice(["R", "t"]))] = np.zeros(int(rng.choice([2, 4, 9]))).tolist()
        cases.append(camera)
    return cases


def _draw_cases(count: int, seed: int) -> list[dict]:
    """Frame sizes with render scales and pixel caps around the frame's own pixel count, where the two languages'
    rounding of the drawn size could part."""
    rng = np.random.default_rng(seed)
    cases = []
    for _ in range(count):
        width, height = int(rng.integers(1, 2049)), int(rng.integers(1, 2049))
        scale = float(rng.choice([1.0, 0.75, 0.5, 0.1, rng.uniform(0.1, 1.0)]))
        cap = rng.choice([None, 1, width * height, int(width * height * rng.uniform(0.01, 1.2)) + 1])
        cases.append({"width": width, "height": height, "render_scale": scale,
                      "max_draw_pixels": None if cap is None else int(cap)})
    return cases


def _node(windows: list[dict], cameras: list[object], folder: Path, draws: list[dict] = ()) -> dict:
    node = shutil.which("node")
    need(None if node else "node is missing (Debian's npm brings it)", BROWSER_INSTALL)
    listing = folder / "cases.json"
    listing.write_text(json.dumps({
        "windows": [{**case, "audio": base64.b64encode(case["audio"].tobytes()).decode()} for case in windows],
        "cameras": cameras, "draws": list(draws)}))
    script = folder / "twins.mjs"
    script.write_text(SCRIPT % {"drive_js": json.dumps((ROOT / "web" / "src" / "drive.js").as_uri()),
                                "camera_js": json.dumps((ROOT / "web" / "src" / "camera.js").as_uri()),
                                "cases": json.dumps(str(listing))})
    done = subprocess.run([node, str(script)], capture_output=True, text=True, timeout=NODE_TIMEOUT_S)
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout)


def _python_verdict(data: object) -> str:
    try:
        Camera.from_dict(data)
    except CameraError:
        return "refused"
    return "loaded"


@pytest.mark.parametrize("run, seed", [pytest.param("ci", 0, id="ci"),
                                       pytest.param("heavy", 1000, id="heavy", marks=pytest.mark.heavy)])
def test_window_plan_gate_crossfades_camera_checks_and_draw_sizes_match_python(tmp_path, run, seed):
    windows = _window_cases(CASES[run], seed)
    cameras = _camera_cases(CASES[run], seed + 1)
    draws = _draw_cases(CASES[run], seed + 2)
    web = _node(windows, cameras, tmp_path, draws)
    for case, size in zip(draws, web["sizes"], strict=True):
        settings = RenderSettings(render_scale=case["render_scale"], max_draw_pixels=case["max_draw_pixels"])
        assert tuple(size) == settings.draw_size(case["width"], case["height"]), case

    gains_moved = 0
    for index, case in enumerate(windows):
        expression, jaw = translate_audio(_fake_translator(case["spf"]), case["audio"], case["spf"], case["window"],
                                          case["context"], case["crossfade"], case["gate"])
        python = np.concatenate([expression, jaw], axis=-1)
        page = np.frombuffer(base64.b64decode(web["rows"][index]), np.float32).reshape(python.shape)
        # Rows agree bit for bit but where a window's gain is on the ramp: numpy sums the window's squares pairwise
        # and the page in order, so the float64 level can differ in its last bits, which may move the float32 gain
        # by one unit in the last place (and the rows it scales by as much).
        exact = np.array_equal(page, python)
        gains_moved += not exact
        assert exact or np.allclose(page, python, rtol=2.5e-7, atol=0), (
            f"case {index} ({ {k: v for k, v in case.items() if k != 'audio'} }, {case['audio'].size} samples): "
            f"rows differ by up to {np.abs(page - python).max():.3g}")
    assert gains_moved <= math.ceil(0.1 * len(windows)), f"{gains_moved} of {len(windows)} cases not bit-identical"

    expected = [_python_verdict(data) for data in cameras]
    disagreements = [(data, python, page) for data, python, page in zip(cameras, expected, web["verdicts"], strict=True)
                     if python != page]
    assert not disagreements, f"{len(disagreements)} camera verdicts differ, first: {disagreements[0]}"
    assert expected.count("loaded") >= len(cameras) // 6 and expected.count("refused") >= len(cameras) // 3


LOUDNESS_SCRIPT = """
import fs from 'node:fs';
import { framePowers, loudnessMoved, madeAfter, windowLoudness } from %(stream_js)s;
import { REFRESHED_FRAMES } from %(generated_js)s;
const cases = JSON.parse(fs.readFileSync(%(cases)s, 'utf8'));
const verdicts = cases.map((c) => {
  const audio = new Float32Array(new Uint8Array(Buffer.from(c.audio, 'base64')).buffer);
  const powers = framePowers(audio, c.frame);
  let made = new Float64Array(REFRESHED_FRAMES);
  const out = [];
  for (let end = c.batch; end <= powers.length; end += c.batch) {
    const now = windowLoudness(powers.subarray(0, end));
    out.push(loudnessMoved(now, made));
    made = madeAfter(made, c.batch, out[out.length - 1], now);
  }
  return out;
});
console.log(JSON.stringify(verdicts));
"""


def test_the_loudness_gate_matches_python(tmp_path):
    """web/src/stream.js `framePowers`, `windowLoudness`, `loudnessMoved` and `madeAfter` against
    runtime/translate_stream.py `frame_power`, `window_loudness`, `loudness_moved` and `made_after` (which graph a
    stream's call runs): the same verdict for every call of seeded audio in pieces of speech-like, quiet and silent
    levels, fed 1, 2 or 8 frames a call."""
    from gaussiantalker.runtime.translate_stream import (
        REFRESHED_FRAMES,
        frame_power,
        loudness_moved,
        made_after,
        window_loudness,
    )

    node = shutil.which("node")
    need(None if node else "node is missing (Debian's npm brings it)", BROWSER_INSTALL)
    rng = np.random.default_rng(7)
    cases = []
    for _ in range(40):
        frame = int(rng.choice([640, 320]))
        levels = rng.choice([0.0, 1e-4, 0.01, 0.1, 0.3], size=int(rng.integers(1, 6)))
        pieces = [level * rng.standard_normal(frame * int(rng.integers(1, 40))) for level in levels]
        cases.append({"frame": frame, "batch": int(rng.choice([1, 2, 8])),
                      "audio": np.concatenate(pieces).astype(np.float32)})
    listing = tmp_path / "loudness.json"
    listing.write_text(json.dumps([{"frame": c["frame"], "batch": c["batch"],
                                    "audio": base64.b64encode(c["audio"].tobytes()).decode()} for c in cases]))
    script = tmp_path / "loudness.mjs"
    script.write_text(LOUDNESS_SCRIPT % {"stream_js": json.dumps((ROOT / "web" / "src" / "stream.js").as_uri()),
                                         "generated_js": json.dumps((ROOT / "web" / "src" / "generated.js").as_uri()),
                                         "cases": json.dumps(str(listing))})
    done = subprocess.run([node, str(script)], capture_output=True, text=True, timeout=NODE_TIMEOUT_S)
    assert done.returncode == 0, done.stderr[-2000:]
    moved = 0
    for case, page in zip(cases, json.loads(done.stdout), strict=True):
        powers, made, python = frame_power(case["audio"].reshape(-1, case["frame"])), np.zeros(REFRESHED_FRAMES), []
        for end in range(case["batch"], powers.shape[0] + 1, case["batch"]):
            now = window_loudness(powers[:end])
            python.append(loudness_moved(now, made))
            made = made_after(made, case["batch"], python[-1], now)
        assert page == python, (case["frame"], case["batch"])
        moved += sum(python)
    assert 0 < moved < sum(len(p) for p in json.loads(done.stdout))  # both verdicts occur
