"""The MNN backend (docs/mnn.md): `gt-export --mnn` stores each graph as an MNN model, offline and without
installing anything; `TalkingHead(backend="mnn")` runs them. Tolerances:

* graph outputs, MNN vs onnxruntime on the same inputs: max |mnn - ort| <= MNN_RTOL (3e-5) * max |ort| per output
  (both run the same decoded float32 weights; measured ~3e-7 on the translator and up to 1.1e-5 on the
  deformation graph's covariances of the opaque demo head's large splats);
* frames of a driven clip, MNN backend vs onnxruntime backend: >= 50 dB 8-bit PSNR (the SDK's parity bound;
  measured ~77-80 dB: what remains is rounding and rare depth-order flips of near-equal depths).

The tests need the `mnn` extra; they are skipped without it, except in CI (`CI` set), which installs it.
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import json
import os
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from gaussiantalker.exporter.export.mnn_export import convert_to_mnn, mnn_compatible
from gaussiantalker.exporter.export.speech import synth_speech
from gaussiantalker.exporter.verify.bundle_verify import MNN_RTOL, _agreement_cases, verify_backend_agreement
from gaussiantalker.runtime.head import TalkingHead
from gaussiantalker.sdk.bundle import Bundle
from gaussiantalker.sdk.errors import BundleError, RenderError
from gaussiantalker.sdk.image import psnr_db

HAS_MNN = importlib.util.find_spec("MNN") is not None
if not HAS_MNN and os.environ.get("CI"):
    raise RuntimeError("CI must install the mnn extra (.ci/install) so that the MNN backend is tested")
needs_mnn = pytest.mark.skipif(not HAS_MNN, reason="the mnn extra is not installed")

SIZE = (128, 128)
MIN_FRAME_PSNR_DB = 50.0


def _installed() -> set[tuple[str, str]]:
    """(name, version) of every installed distribution, read afresh from disk."""
    return {(dist.metadata["Name"], dist.version) for dist in importlib.metadata.distributions()}


@pytest.fixture(scope="module")
def mnn_export(small_export, tmp_path_factory):
    """The small speaker exported with --mnn (its recorded torch.onnx graphs replayed), with the parent's socket
    creation made to fail and the installed distributions listed before and after."""
    from conftest import replaying_onnx_exports

    from gaussiantalker.exporter.export.bundle_export import export_bundle

    path = tmp_path_factory.mktemp("mnn") / "small_mnn.gtb"
    before = _installed()
    with pytest.MonkeyPatch.context() as patch, replaying_onnx_exports(small_export.protos):
        def refuse(*args, **kwargs):
            raise OSError("socket creation refused by the test")

        patch.setattr(socket, "socket", refuse)
        patch.setattr(socket, "create_connection", refuse)
        result = export_bundle(small_export.speaker, path, progress=False, mnn=True)
    return {"path": path, "result": result, "before": before, "after": _installed()}


@needs_mnn
def test_mnn_export_stores_every_graph_offline_and_installs_nothing(mnn_export):
    """Every graph gets a checksummed `mnn/<graph>` entry and a manifest row with its ONNX signature; the export
    ran with sockets refused and left the installed packages exactly as they were."""
    bundle = Bundle(mnn_export["path"])
    section = bundle.manifest["mnn"]
    assert section["converter"].startswith("MNN ")
    assert sorted(section["graphs"]) == bundle.graph_names() == ["deform", "translator", "translator_stream",
                                                                  "translator_stream_steady"]
    for name, entry in section["graphs"].items():
        assert entry["buffer"] == f"mnn/{name}"
        assert entry["inputs"] == bundle.graph_info(name)["inputs"]
        model = bundle.buffer(entry["buffer"])
        assert model.dtype == np.uint8 and model.size == mnn_export["result"].mnn[name] > 1000
    assert mnn_export["after"] == mnn_export["before"]


@needs_mnn
def test_worker_refuses_network_and_processes():
    """The converter's process refuses Python-level sockets and process creation (the guard the export runs
    the converter under), and reports each attempt."""
    code = textwrap.dedent("""
        import socket, subprocess
        from gaussiantalker.exporter.export.mnn_worker import forbid_side_effects
        attempts = []
        forbid_side_effects(attempts)
        attempts_made = (lambda: socket.socket(), lambda: subprocess.run(["true"]),
                         lambda: __import__("os").system("true"))
        for attempt in attempts_made:
            try:
                attempt()
            except PermissionError:
                pass
        print(attempts)
    """)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert run.stdout.strip() == "['socket.__new__', 'subprocess.Popen', 'os.system']"


def _fake_converter(tmp_path: Path, body: str, monkeypatch) -> None:
    """Put a stand-in for MNN's `_tools` first on the converter process's path."""
    (tmp_path / "_tools.py").write_text(f"def mnnconvert(argv):\n{textwrap.indent(textwrap.dedent(body), '    ')}\n")
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))


@pytest.mark.parametrize(("body", "words"), [
    ("import socket\ntry:\n    socket.socket()\nexcept OSError:\n    pass\nreturn True", "tried socket.__new__"),
    ("import os\nos.system('pip install something')\nreturn True", "tried os.system"),
    ("import os, signal\nos.kill(os.getpid(), signal.SIGSEGV)", "crashed (signal 11)"),
    ("print('These Op Not Support: ONNX::Foo')\nreturn False", "These Op Not Support: ONNX::Foo"),
])
def test_converter_misbehaviour_is_a_clear_export_error(tmp_path, monkeypatch, small_export, body, words):
    """A converter that goes online (even if it swallows the refusal), starts a process, crashes or fails gives
    an export error saying so, never a bundle."""
    _fake_converter(tmp_path, body, monkeypatch)
    with pytest.raises(BundleError, match="MNN's converter") as caught:
        convert_to_mnn(small_export.protos[3], "deform")
    assert words in str(caught.value)


def test_missing_converter_fails_before_exporting(monkeypatch, small_export, tmp_path):
    """--mnn without the extra: an error saying what to install, before any graph is exported."""
    import gaussiantalker.exporter.export.mnn_export as mnn_export_module
    from gaussiantalker.exporter.export.bundle_export import export_bundle

    def not_installed(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(mnn_export_module.importlib.metadata, "version", not_installed)
    with pytest.raises(BundleError, match=r'pip install "gaussiantalker-sdk\[mnn\]"'):
        export_bundle(small_export.speaker, tmp_path / "x.gtb", progress=False, mnn=True)
    assert not (tmp_path / "x.gtb").exists()


def test_compatibility_rewrites_compute_the_same_function(small_export):
    """The graph MNN receives is the same function: onnxruntime gives identical outputs for the rewritten graph
    (Gelu as its erf definition, ReduceL2 as the root of a sum of squares) and the original."""
    import onnxruntime as ort

    from gaussiantalker.exporter.export.mnn_export import fold_constants

    translator = fold_constants(small_export.protos[0])
    rewritten = mnn_compatible(translator)
    ops = {node.op_type for node in rewritten.graph.node}
    assert "Gelu" not in ops and "ReduceL2" not in ops and "Erf" in ops
    audio = synth_speech(1.0, seed=4)[None, : 640 * 25].astype(np.float32)
    outputs = [ort.InferenceSession(m.SerializeToString(), providers=["CPUExecutionProvider"]).run(None,
               {"audio": audio}) for m in (translator, rewritten)]
    for before, after in zip(*outputs, strict=True):
        np.testing.assert_array_equal(before, after)


@needs_mnn
def test_mnn_graphs_agree_with_onnxruntime(mnn_export, small_export):
    """Every graph output within MNN_RTOL of onnxruntime's, relative to the output's largest magnitude."""
    with TalkingHead(mnn_export["path"], resolution=SIZE) as ort_head, \
            TalkingHead(mnn_export["path"], resolution=SIZE, backend="mnn") as mnn_head:
        rows = verify_backend_agreement(ort_head, mnn_head, _agreement_cases(small_export.speaker, ort_head))
    assert sorted(rows) == ["deform", "translator", "translator_stream", "translator_stream_steady"]
    for name, row in rows.items():
        assert row["finite"] and row["max_rel_err"] <= MNN_RTOL, (name, row)


@needs_mnn
@pytest.mark.parametrize("frames", [1, 7, 250])
def test_mnn_translator_takes_any_audio_length(mnn_export, frames):
    """Dynamic audio length: MNN resizes the translator's input per call (1 frame to 10 s)."""
    audio = synth_speech(frames * 640 / 16000 + 0.1, seed=frames)[None, : 640 * frames].astype(np.float32)
    with TalkingHead(mnn_export["path"], resolution=SIZE, backend="mnn") as mnn_head, \
            TalkingHead(mnn_export["path"], resolution=SIZE) as ort_head:
        got = mnn_head.frame_renderer.graphs.run("translator", {"audio": audio})
        expected = ort_head.frame_renderer.graphs.run("translator", {"audio": audio})
    for name, value in expected.items():
        assert got[name].shape == value.shape == (1, frames, value.shape[-1])
        assert np.abs(got[name] - value).max() <= MNN_RTOL * np.abs(value).max()


@needs_mnn
def test_mnn_frames_match_onnxruntime(mnn_export):
    """The driven clip's frames from both backends at >= 50 dB; the MNN backend is selected by name."""
    audio = synth_speech(1.0, seed=5)
    with TalkingHead(mnn_export["path"], resolution=SIZE) as ort_head, \
            TalkingHead(mnn_export["path"], resolution=SIZE, backend="mnn") as mnn_head:
        assert type(mnn_head.frame_renderer.graphs).__name__ == "MnnBackend"
        pairs = list(zip(ort_head.frames(audio, 16000), mnn_head.frames(audio, 16000), strict=True))
    assert len(pairs) == 25
    worst = min(psnr_db(a, b) for a, b in pairs)
    assert worst >= MIN_FRAME_PSNR_DB, worst


@needs_mnn
def test_mnn_inpaint_graph_sanitises_nan(tmp_path, inpaint_export):
    """The inpainting generator's NaN guard (x != x, MNN has no IsNaN) survives conversion: NaN in, finite out
    (the session's F graph, conftest `inpaint_export`: its weights do not matter here)."""
    import onnx

    from gaussiantalker.exporter.export.mnn_export import fold_constants
    from gaussiantalker.runtime.mnn_backend import import_mnn

    model = inpaint_export.proto
    path = tmp_path / "inpaint.mnn"
    path.write_bytes(convert_to_mnn(mnn_compatible(fold_constants(model)), "inpaint"))
    assert not any(node.op_type == "IsNaN" for node in model.graph.node), onnx.helper.printable_graph(model.graph)
    nn, expr = import_mnn()
    module = nn.load_module_from_file(str(path), ["image", "mask", "coverage"], ["inpainted"], thread_num=1)
    image = np.full((1, 3, 32, 48), np.nan, np.float32)
    image[0, :, :, :10] = np.inf
    mask = np.random.default_rng(0).random((1, 1, 32, 48)).astype(np.float32)
    out = module.forward([expr.const(a, list(a.shape), expr.NCHW) for a in (image, mask, mask)])[0]
    result = np.array(expr.convert(out, expr.NCHW).read())
    assert result.shape == (1, 3, 32, 48) and np.isfinite(result).all()


# -- bad input ---------------------------------------------------------------------------------------------------


def test_bundle_without_mnn_graphs_says_to_reexport(small_export):
    with pytest.raises(BundleError, match="gt-export --mnn"):
        TalkingHead(small_export.path, resolution=SIZE, backend="mnn")


def test_unknown_backend_is_refused(small_export):
    with pytest.raises(RenderError, match="unknown graph backend 'tensorrt'.*onnxruntime, mnn"):
        TalkingHead(small_export.path, resolution=SIZE, backend="tensorrt")


@needs_mnn
def test_missing_mnn_says_what_to_install(mnn_export, monkeypatch):
    """backend="mnn" without the extra: the error names the pip command (MNN hidden from imports here)."""
    for name in [n for n in sys.modules if n == "MNN" or n.startswith("MNN.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "MNN", None)
    with pytest.raises(BundleError, match=r'pip install "gaussiantalker-sdk\[mnn\]"'):
        TalkingHead(mnn_export["path"], resolution=SIZE, backend="mnn")


@needs_mnn
def test_damaged_mnn_entry_fails_its_checksum(mnn_export, tmp_path):
    """A flipped byte inside `mnn/deform` fails at load, naming the entry, on either backend's full check."""
    bundle = Bundle(mnn_export["path"])
    entry = bundle.manifest["buffers"]["mnn/deform"]
    data = bytearray(Path(mnn_export["path"]).read_bytes())
    data[bundle.payload_start + entry["offset"] + entry["nbytes"] // 2] ^= 0x20
    damaged = tmp_path / "damaged.gtb"
    damaged.write_bytes(bytes(data))
    with pytest.raises(BundleError, match=r"checksum mismatch in buffer 'mnn/deform'"):
        TalkingHead(damaged, resolution=SIZE, backend="mnn")
    with pytest.raises(BundleError, match=r"checksum mismatch in buffer 'mnn/deform'"):
        Bundle(damaged).verify_all()


@needs_mnn
def test_speaker_expression_width_is_checked_on_mnn_too(mnn_export, tmp_path):
    """A manifest whose speaker n_expr disagrees with the graphs is refused at load by the MNN backend as by
    onnxruntime's (drives are built from n_expr; the graphs would fail mid-video)."""
    from test_bundle import _rewrite_manifest

    lying = tmp_path / "lying.gtb"
    lying.write_bytes(Path(mnn_export["path"]).read_bytes())
    _rewrite_manifest(lying, lambda manifest: manifest["speaker"].update(n_expr=30, expression_names=[]))
    for backend in ("mnn", "onnxruntime"):
        with pytest.raises(BundleError, match=r"manifest speaker n_expr is 30 but graph 'deform' input 'expression' "
                                              r"has \d+ coefficients"):
            TalkingHead(lying, resolution=SIZE, backend=backend)


@needs_mnn
def test_verify_report_covers_mnn_graphs(mnn_export, small_export):
    """gt-export --verify's report gains the MNN rows (graphs vs onnxruntime, frames), all passing."""
    from gaussiantalker.exporter.verify.bundle_verify import format_report, verify_bundle

    report = verify_bundle(small_export.speaker, mnn_export["path"], frames=4, resolution=SIZE, progress=False)
    mnn = report["mnn"]
    assert report["passed"] and mnn["passed"] and sorted(mnn["graphs"]) == ["deform", "translator", "translator_stream",
                                                                                  "translator_stream_steady"]
    assert mnn["frames"] == 4 and mnn["min_psnr_db"] >= MIN_FRAME_PSNR_DB
    text = format_report(report)
    assert "mnn deform" in text and "mnn frames" in text
    json.dumps(mnn)  # the report is written as JSON by --report


@needs_mnn
def test_backends_bench_measures_both_backends(mnn_export):
    """`gt-bench --backends`' measurement and table run end to end on a small bundle (speed is not judged here)."""
    from tools.bench.backends import CASES, format_table, measure_case

    audio = synth_speech(0.6, seed=2)
    runs = {label: [measure_case(mnn_export["path"], backend, threads, 64, audio, 16000)]
            for label, backend, threads in CASES}
    for case_runs in runs.values():
        run = case_runs[0]
        assert run["frames"] == 15 and run["fps"] > 0
        assert set(run["graphs_ms"]) == {"translator 10 s", "deformation"}
    table = format_table(runs, 64, 0.6, 1, Path("speaker.ckpt"), 1.0)
    assert table.count("\n| ") == len(CASES) + 1 and "| mnn 2 threads |" in table
