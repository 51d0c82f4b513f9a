"""The built-in voice drivers (docs/voice.md) in onnxruntime-web, the version the browser player pins
(web/package-lock.json): its WebAssembly backend, run here by node, gives the ARKit and FLAME models' outputs
within 1e-5 of onnxruntime's (measured: 2.5e-7; float32 kernels that sum in another order differ by a few ulps),
and so does their streaming form fed a frame a call.
Needs node and web/'s npm install (.ci/browser installs both in CI, where this test fails without them)."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import onnxruntime as ort
from ci_tools import BROWSER_INSTALL, need

from gaussiantalker.exporter.voice.data import load_utterance
from gaussiantalker.exporter.voice.paths import ARKIT_MODEL, FLAME_MODEL

ROOT = Path(__file__).resolve().parent.parent
ORT_NODE = ROOT / "web" / "node_modules" / "onnxruntime-web" / "dist" / "ort.node.min.mjs"
CLIP = ROOT / "tests" / "data" / "voice_heldout"
# Runs one model on the audio in a file and prints every output as JSON (flattened, with its dims).
SCRIPT = """
import * as ort from %(ort)s;
import fs from 'fs';
ort.env.wasm.numThreads = 1;
const bytes = fs.readFileSync(%(audio)s);
const audio = new Float32Array(bytes.buffer, bytes.byteOffset, bytes.byteLength / 4);
const session = await ort.InferenceSession.create(fs.readFileSync(%(model)s), {executionProviders: ['wasm']});
const out = await session.run({[session.inputNames[0]]: new ort.Tensor('float32', audio, [1, audio.length])});
const result = {};
for (const name of session.outputNames) result[name] = {dims: out[name].dims, data: Array.from(out[name].data)};
console.log(JSON.stringify(result));
"""


def test_voice_models_run_in_onnxruntime_web(tmp_path):
    node = shutil.which("node")
    need(None if node and ORT_NODE.is_file() else "node or web/'s npm install (onnxruntime-web) is missing "
         "(cd web && npm ci)", BROWSER_INSTALL)
    audio = load_utterance(CLIP).audio[: 64_000].astype(np.float32)  # 4 s: 100 frames
    (tmp_path / "audio.f32").write_bytes(audio.tobytes())
    for model in (ARKIT_MODEL, FLAME_MODEL):
        script = tmp_path / "run.mjs"
        script.write_text(SCRIPT % {"ort": json.dumps(str(ORT_NODE)), "audio": json.dumps(str(tmp_path / "audio.f32")),
                                    "model": json.dumps(str(model))})
        done = subprocess.run([node, str(script)], capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stderr[-2000:]
        web = json.loads(done.stdout)
        session = ort.InferenceSession(str(model), providers=["CPUExecutionProvider"])
        names = [o.name for o in session.get_outputs()]
        native = dict(zip(names, session.run(None, {session.get_inputs()[0].name: audio[None]}), strict=True))
        assert sorted(web) == sorted(native)
        for name, values in native.items():
            got = np.asarray(web[name]["data"], np.float32).reshape(web[name]["dims"])
            assert got.shape == values.shape and values.shape[1] == 100
            np.testing.assert_allclose(got, values, atol=1e-5, rtol=0)


# Runs a streaming graph frame by frame from the state it is given (the rest state) and prints every call's rows.
STREAM_SCRIPT = """
import * as ort from %(ort)s;
import fs from 'fs';
ort.env.wasm.numThreads = 1;
const read = (path) => {
  const b = fs.readFileSync(path);
  return new Float32Array(b.buffer, b.byteOffset, b.byteLength / 4);
};
const audio = read(%(audio)s);
let state = read(%(state)s);
const session = await ort.InferenceSession.create(fs.readFileSync(%(model)s), {executionProviders: ['wasm']});
const rows = [];
for (let first = 0; first + 640 <= audio.length; first += 640) {
  const out = await session.run({audio: new ort.Tensor('float32', audio.slice(first, first + 640), [1, 1, 640]),
    state: new ort.Tensor('float32', state, [1, state.length]), keep: new ort.Tensor('float32', [1], [1])});
  state = out.state_out.data;
  rows.push(Array.from(out[%(output)s].data));
}
console.log(JSON.stringify(rows));
"""


def test_the_streaming_voice_runs_in_onnxruntime_web(tmp_path):
    """The streaming graph a bundle carries beside the voice (docs/live.md, "Streaming translators"), fed a frame a
    call in onnxruntime-web from the rest state: every row within 1e-5 of onnxruntime's stream."""
    import onnx

    from gaussiantalker.exporter.export.voice_stream import stream_model_of

    node = shutil.which("node")
    need(None if node and ORT_NODE.is_file() else "node or web/'s npm install (onnxruntime-web) is missing "
         "(cd web && npm ci)", BROWSER_INSTALL)
    audio = load_utterance(CLIP).audio[: 40 * 640].astype(np.float32)
    (tmp_path / "audio.f32").write_bytes(audio.tobytes())
    for model, output in ((ARKIT_MODEL, "blendshapes"), (FLAME_MODEL, "expression")):
        stream = stream_model_of(onnx.load(str(model)))
        (tmp_path / "stream.onnx").write_bytes(stream.SerializeToString())
        session = ort.InferenceSession(stream.SerializeToString(), providers=["CPUExecutionProvider"])
        size = session.get_inputs()[1].shape[1]
        state = session.run(["state_out"], {"audio": np.zeros((1, 32, 640), np.float32),
                                            "state": np.zeros((1, size), np.float32),
                                            "keep": np.array([32], np.float32)})[0]
        (tmp_path / "state.f32").write_bytes(state.astype(np.float32).tobytes())
        script = tmp_path / "stream.mjs"
        script.write_text(STREAM_SCRIPT % {key: json.dumps(str(value)) for key, value in (
            ("ort", ORT_NODE), ("audio", tmp_path / "audio.f32"), ("state", tmp_path / "state.f32"),
            ("model", tmp_path / "stream.onnx"), ("output", output))})
        done = subprocess.run([node, str(script)], capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stderr[-2000:]
        web = np.asarray(json.loads(done.stdout), np.float32)
        native = []
        for first in range(0, audio.shape[0], 640):
            out = session.run([output, "state_out"], {"audio": audio[None, None, first:first + 640],
                                                      "state": state, "keep": np.array([1], np.float32)})
            native.append(out[0].reshape(-1))
            state = out[1]
        assert web.shape == (40, native[0].shape[0])
        np.testing.assert_allclose(web, np.stack(native), atol=1e-5, rtol=0)
