"""Bad files on a REAL bundle and checkpoint (the 2k-Gaussian speaker): every kind of damage is an SDK error
naming the section, and exports are atomic. Each case records what it observed in the stability table.

`tests/test_bundle.py` and `tests/test_checkpoint.py` cover the format on tiny synthetic files; here the damage
is done to a bundle the exporter really wrote and loaded the way an application loads it: `Bundle(path)` (then
`verify_all()`, which reads every entry) and `TalkingHead(path)` (reads and checksums every graph and buffer,
opens onnxruntime sessions).
"""

from __future__ import annotations

import copy
import hashlib
import json
import os
import pickle
import re
import shutil
import signal
import struct
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

import gaussiantalker.exporter.export.onnx_export as onnx_export_module
from gaussiantalker.exporter.export.bundle_export import export_bundle
from gaussiantalker.exporter.export.checkpoint import load_checkpoint, save_checkpoint
from gaussiantalker.runtime import TalkingHead
from gaussiantalker.sdk.bundle import _HEADER, ALIGN, HEADER_SIZE, Bundle, _align
from gaussiantalker.sdk.errors import BundleError, CheckpointError

HEAD_SIZE = (32, 32)


# -- fixtures and helpers ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def real(small_speaker, small_export, tmp_path_factory) -> SimpleNamespace:
    """The small speaker's session bundle, copied here, with its ONNX protos (later exports skip torch.onnx)."""
    root = tmp_path_factory.mktemp("stability_files")
    shutil.copy(small_export.path, root / "good.gtb")
    protos = small_export.protos
    bundle = Bundle(root / "good.gtb")
    entries = sorted(((kind[:-1], name, entry) for kind in ("graphs", "buffers")
                      for name, entry in bundle.manifest[kind].items()), key=lambda item: item[2]["offset"])
    return SimpleNamespace(path=root / "good.gtb", data=(root / "good.gtb").read_bytes(), protos=protos,
                           manifest=json.loads(json.dumps(bundle.manifest)), payload_start=bundle.payload_start,
                           entries=entries, speaker=small_speaker, root=root)


@pytest.fixture(scope="module")
def checkpoint(real) -> SimpleNamespace:
    """The same speaker saved as a checkpoint, and its payload as plain tensors/dicts."""
    path = save_checkpoint(real.speaker, real.root / "speaker.ckpt")
    return SimpleNamespace(path=path, payload=torch.load(path, weights_only=True))


def _text(exc: BaseException, path: Path) -> str:
    """An error message with the file path as FILE (its test-named folders would match anything)."""
    text = str(exc).replace(str(path), "FILE")
    return text.removeprefix("FILE: ")


def _message(exc: BaseException, path: Path) -> str:
    """First line of an error message without the (temporary) file path, for the table."""
    return _text(exc, path).splitlines()[0]


def _observed(exc: BaseException, path: Path, limit: int = 90) -> str:
    return f"{type(exc).__name__}: {_message(exc, path)[:limit]}"


def _open_head(path: Path) -> None:
    TalkingHead(path, resolution=HEAD_SIZE).close()


def _bundle_refuses(path: Path) -> BundleError:
    """Bundle(path) or its full read (verify_all) raises BundleError; anything else fails the test."""
    with pytest.raises(BundleError) as caught:
        Bundle(path).verify_all()
    return caught.value


def _runtime_refuses(path: Path) -> BundleError:
    """TalkingHead(path) raises BundleError (not KeyError, TypeError, an onnxruntime error, ...)."""
    with pytest.raises(BundleError) as caught:
        _open_head(path)
    return caught.value


def _with_manifest(real: SimpleNamespace, edit, path: Path, header_version: tuple[int, int] | None = None) -> Path:
    """Write the real bundle with `edit(manifest)` applied and a VALID digest: a well-formed file that lies."""
    manifest = copy.deepcopy(real.manifest)
    edit(manifest)
    raw = json.dumps(manifest).encode()
    major, minor = header_version or tuple(real.manifest["version"])
    header = _HEADER.pack(b"GTBUNDLE", major, minor, 0, len(raw), hashlib.sha256(raw).digest())
    header += b"\0" * (HEADER_SIZE - len(header))
    path.write_bytes(header + raw + b"\0" * (_align(len(raw)) - len(raw)) + real.data[real.payload_start:])
    return path


def _with_padding(real: SimpleNamespace, path: Path) -> SimpleNamespace:
    """`real`, or where its manifest fills its last 64 bytes (no zero padding after it) the same manifest written
    with a space more at its end, so that padding follows it."""
    manifest_len = _HEADER.unpack_from(real.data)[4]
    if manifest_len % ALIGN:
        return real
    raw = real.data[HEADER_SIZE:HEADER_SIZE + manifest_len] + b" "
    header = _HEADER.pack(b"GTBUNDLE", *real.manifest["version"], 0, len(raw), hashlib.sha256(raw).digest())
    header += b"\0" * (HEADER_SIZE - len(header))
    data = header + raw + b"\0" * (_align(len(raw)) - len(raw)) + real.data[real.payload_start:]
    path.write_bytes(data)
    return SimpleNamespace(data=data, payload_start=Bundle(path).payload_start)


def _flipped(real: SimpleNamespace, offset: int, path: Path) -> Path:
    data = bytearray(real.data)
    data[offset] ^= 0x20
    path.write_bytes(bytes(data))
    return path


# -- baseline ---------------------------------------------------------------------------------------------------


def test_undamaged_real_bundle_loads_and_renders(real, stability):
    """The copy every other test damages is itself good: both loaders accept it and a frame renders."""
    Bundle(real.path).verify_all()
    with TalkingHead(real.path, resolution=HEAD_SIZE) as head:
        frame = head.render_params()
    assert frame.shape == (*HEAD_SIZE[::-1], 3)
    stability.record("bundle", "undamaged real bundle (2k Gaussians)", f"loads; renders a {frame.shape} frame")


# -- truncation -------------------------------------------------------------------------------------------------


def _section_cuts(real: SimpleNamespace) -> list[tuple[int, str, str]]:
    """(cut length, case, words the error must contain) at every section boundary of the real bundle."""
    manifest_end = HEADER_SIZE + _HEADER.unpack_from(real.data)[4]
    cuts = [(0, "empty file", "header"), (10, "inside the header", "header"),
            (HEADER_SIZE, "end of header", "manifest"),
            ((HEADER_SIZE + manifest_end) // 2, "inside manifest", "manifest"),
            (manifest_end - 1, "one byte short of the manifest", "manifest")]
    if manifest_end < real.payload_start:
        cuts.append((manifest_end, "end of manifest (padding missing)", "after the manifest"))
    for index, (kind, name, entry) in enumerate(real.entries):
        start = real.payload_start + entry["offset"]
        cuts.append((start, f"start of {kind} {name!r}", f"{kind} {name!r}"))
        later = real.entries[index + 1] if index + 1 < len(real.entries) else None
        named = f"{later[0]} {later[1]!r}" if later else "padding after the last entry"
        cuts.append((start + entry["nbytes"], f"end of {kind} {name!r}", named))
    cuts.append((len(real.data) - 1, "one byte short of the end",
                 "padding after the last entry" if real.data.endswith(b"\0") else real.entries[-1][1]))
    return [cut for cut in cuts if cut[0] < len(real.data)]


def test_truncated_at_every_section_boundary(real, tmp_path, stability):
    """Both loaders say 'truncated' and name the first section the cut leaves incomplete."""
    path = tmp_path / "cut.gtb"
    shutil.copy(real.path, path)
    buffer_rows = []
    for cut, case, named in sorted(_section_cuts(real), reverse=True):  # shrink one copy step by step
        os.truncate(path, cut)
        for exc in (_bundle_refuses(path), _runtime_refuses(path)):
            assert "truncated" in _text(exc, path) and named in _text(exc, path), (case, str(exc))
        if " buffer " in f" {case}":
            buffer_rows.append(_observed(exc, path, 60))
        else:
            stability.record("bundle", f"truncated at {case} ({cut} bytes)", _observed(exc, path))
    stability.record("bundle", f"truncated at the start and the end of each of {len(buffer_rows) // 2} buffers",
                     f"all {len(buffer_rows)} cuts: BundleError from Bundle and TalkingHead naming the entry cut "
                     f"short, e.g. {buffer_rows[-1]}")


# -- flipped bytes ----------------------------------------------------------------------------------------------


HEADER_FIELDS = [(0, "magic", "bad magic"), (8, "format major version", "not supported"),
                 (10, "format minor version", "manifest says"), (12, "reserved field", "reserved header bytes"),
                 (16, "manifest length (low byte)", "manifest"), (23, "manifest length (high byte)", "manifest claims"),
                 (24, "manifest digest", "manifest checksum mismatch"), (60, "header padding", "reserved header")]


@pytest.mark.parametrize("offset,field,expected", HEADER_FIELDS, ids=[f[1] for f in HEADER_FIELDS])
def test_flipped_byte_in_header_field(real, tmp_path, stability, offset, field, expected):
    """Every header byte matters: each field's flip is refused by both loaders with the field's problem."""
    path = _flipped(real, offset, tmp_path / "flip.gtb")
    for exc in (_bundle_refuses(path), _runtime_refuses(path)):
        assert expected in _text(exc, path)
    stability.record("bundle", f"flipped byte in header: {field}", _observed(exc, path))


def test_flipped_byte_in_manifest_and_its_padding(real, tmp_path, stability):
    """A flip in the manifest fails its digest; one in the zero padding after it is refused too."""
    manifest_len = _HEADER.unpack_from(real.data)[4]
    padded = _with_padding(real, tmp_path / "padded.gtb")
    cases = ((real, HEADER_SIZE + manifest_len // 2, "manifest", "manifest checksum mismatch"),
             (padded, padded.payload_start - 1, "padding after the manifest", "padding after the manifest"))
    for source, offset, case, expected in cases:
        path = _flipped(source, offset, tmp_path / "flip.gtb")
        for exc in (_bundle_refuses(path), _runtime_refuses(path)):
            assert expected in _text(exc, path)
        stability.record("bundle", f"flipped byte in the {case}", _observed(exc, path))


def test_flipped_byte_in_every_graph_and_buffer(real, tmp_path, stability):
    """Bundle.verify_all and TalkingHead both report a checksum mismatch naming the damaged entry."""
    buffer_rows = []
    for kind, name, entry in real.entries:
        path = _flipped(real, real.payload_start + entry["offset"] + entry["nbytes"] // 2, tmp_path / "flip.gtb")
        for exc in (_bundle_refuses(path), _runtime_refuses(path)):
            assert f"checksum mismatch in {kind} {name!r}" in _text(exc, path)
            assert "onnxruntime" not in str(exc)  # found before any graph reaches onnxruntime
        if kind == "graph":
            stability.record("bundle", f"flipped byte in graph {name!r}", _observed(exc, path))
        else:
            buffer_rows.append(_observed(exc, path, 60))
    stability.record("bundle", f"flipped byte in each of the {len(buffer_rows)} buffers",
                     f"all {len(buffer_rows)}: BundleError from Bundle.verify_all and TalkingHead naming the buffer, "
                     f"e.g. {buffer_rows[-1]}")


# -- a manifest that lies (valid digest) ------------------------------------------------------------------------


def _buffer(name: str, **fields):
    return lambda m: m["buffers"][name].update(fields)


def _io(graph: str, kind: str, index: int, **fields):
    return lambda m: m["graphs"][graph][kind][index].update(fields)


RUNTIME_LIES = {
    "buffer shape transposed (same bytes)": (_buffer("deform/log_scale", shape=[2000, 3]),
                                             "initializer 'log_scale' is float32 [3, 2000]"),
    "buffer shape flattened (same bytes)": (_buffer("deform/sh_rest", shape=[90000]),
                                            "initializer 'sh_rest'"),
    "buffer dtype float32 -> int32 (same bytes)": (_buffer("deform/rest_points", dtype="int32"),
                                                   "buffer 'deform/rest_points' is int32"),
    "graph input renamed": (_io("deform", "inputs", 0, name="expr"), "graph 'deform' inputs are"),
    "graph input dtype": (_io("deform", "inputs", 1, dtype="float16"), "input 'flame_pose' is tensor(float)"),
    "graph input rank": (_io("deform", "inputs", 2, shape=["batch", 3, 1]), "input 'head_translation'"),
    "graph input fixed size": (_io("deform", "inputs", 0, shape=["batch", 30]), "input 'expression'"),
    "graph output renamed": (_io("translator", "outputs", 1, name="jaw"), "graph 'translator' outputs are"),
    "graph output dropped": (lambda m: m["graphs"]["deform"]["outputs"].pop(), "graph 'deform' outputs are"),
    "initializer the graph does not have": (
        lambda m: m["graphs"]["deform"]["initializers"].update(bogus="pose_track"), "has no initializer 'bogus'"),
    "initializer left out (graph would read external file 'bundle')": (
        lambda m: m["graphs"]["deform"]["initializers"].pop("rest_points"),
        "tensor 'rest_points' wants external data"),
    "missing graph 'translator'": (lambda m: m["graphs"].pop("translator"), "lacks the 'translator' graph"),
    "missing graph 'deform'": (lambda m: m["graphs"].pop("deform"), "lacks the 'deform' graph"),
    "missing 'speaker' section": (lambda m: m.pop("speaker"), "manifest has no 'speaker' section"),
    "missing 'camera' section": (lambda m: m.pop("camera"), "manifest has no 'camera' section"),
    "'speaker' section not a table": (lambda m: m.update(speaker=[]), "'speaker' section is not a table"),
    "'camera' section invalid": (lambda m: m["camera"].pop("fx"), "'camera' section is invalid"),
    # (Its expression names go too: 20 names for 30 coefficients is a config error of its own.)
    "speaker n_expr disagrees with graphs": (lambda m: m["speaker"].update(n_expr=30, expression_names=[]),
                                             "n_expr is 30"),
    "speaker expression names miscounted": (lambda m: m["speaker"].update(expression_names=["jaw"]),
                                            "1 expression_names for 20 expression coefficients"),
    "speaker fps disagrees with the translator": (lambda m: m["speaker"].update(fps=30),
                                                  "no valid speaker config: config timing disagrees"),
    "speaker config has an unknown key": (lambda m: m["speaker"].update(colour="red"),
                                          "unknown speaker config keys: ['colour']"),
    "pose_track shape [T*6]": (_buffer("pose_track", shape=[900]), "buffer 'pose_track' is float32 [900]"),
}


@pytest.mark.parametrize("case", list(RUNTIME_LIES))
def test_manifest_lie_caught_when_the_runtime_opens_the_graphs(real, tmp_path, monkeypatch, stability, case):
    """Lies only the real ONNX graphs (or the runtime's needs) can expose: TalkingHead says which and where."""
    edit, expected = RUNTIME_LIES[case]
    monkeypatch.chdir(tmp_path)
    (tmp_path / "bundle").write_bytes(b"\0" * 64)  # what onnxruntime would open for a left-out initializer
    path = _with_manifest(real, edit, tmp_path / "lie.gtb")
    exc = _runtime_refuses(path)
    assert expected in _text(exc, path), str(exc)
    stability.record("bundle", f"manifest lies: {case}", _observed(exc, path))


BUNDLE_LIES = {
    "graph needs a buffer the bundle lacks": (lambda m: m["buffers"].pop("deform/blend_basis"),
                                              "needs unknown buffer 'deform/blend_basis'"),
    "buffer shape [null]": (_buffer("pose_track", shape=[None]), "buffer 'pose_track' has a malformed"),
    "buffer shape [150.0, 6]": (_buffer("pose_track", shape=[150.0, 6]), "buffer 'pose_track' has a malformed"),
    "buffer codec a string": (_buffer("pose_track", codec="raw"), "buffer 'pose_track' has a malformed"),
    "fp16 codec on an int64 buffer": (
        _buffer("deform/parent_triangle", codec={"name": "fp16"}, shape=[2000]),
        "codec 'fp16' cannot decode to dtype 'int64'"),
    "buffer nbytes true": (_buffer("pose_track", nbytes=True), "buffer 'pose_track' has an invalid offset/size"),
    "buffer sha256 missing": (lambda m: m["buffers"]["pose_track"].pop("sha256"), "has no valid sha256"),
    "initializers a list": (lambda m: m["graphs"]["deform"].update(initializers=[]), "malformed initializers"),
    "graph inputs not a list": (lambda m: m["graphs"]["deform"].update(inputs=5), "graph 'deform' inputs is malformed"),
    "graph input entry a string": (lambda m: m["graphs"]["translator"]["inputs"].__setitem__(0, "audio"),
                                   "graph 'translator' inputs is malformed"),
    "version field a string": (lambda m: m.update(version="1.0"), "manifest says '1.0'"),
}


@pytest.mark.parametrize("case", list(BUNDLE_LIES))
def test_manifest_lie_caught_by_the_bundle_reader(real, tmp_path, stability, case):
    """Malformed or inconsistent manifest values: BundleError from Bundle itself, never TypeError/KeyError."""
    edit, expected = BUNDLE_LIES[case]
    path = _with_manifest(real, edit, tmp_path / "lie.gtb")
    for exc in (_bundle_refuses(path), _runtime_refuses(path)):
        assert expected in _text(exc, path), str(exc)
    stability.record("bundle", f"manifest lies: {case}", _observed(exc, path))


def test_unknown_major_version(real, tmp_path, stability):
    """A consistent 2.0 bundle (header and manifest agree) is refused by this 1.x reader."""
    path = _with_manifest(real, lambda m: m.update(version=[2, 0]), tmp_path / "v2.gtb", header_version=(2, 0))
    for exc in (_bundle_refuses(path), _runtime_refuses(path)):
        assert "format version 2.0 is not supported" in _text(exc, path)
    stability.record("bundle", "unknown major version 2.0", _observed(exc, path))


def test_graph_that_is_not_onnx(real, tmp_path, stability):
    """Garbage graph bytes with a matching checksum: BundleError naming the graph, not a protobuf crash."""
    kind, name, entry = next(e for e in real.entries if e[:2] == ("graph", "deform"))
    start = real.payload_start + entry["offset"]
    garbage = bytes((i * 37 + 11) % 256 for i in range(entry["nbytes"]))
    patched = real.data[:start] + garbage + real.data[start + entry["nbytes"]:]
    real_like = SimpleNamespace(manifest=real.manifest, payload_start=real.payload_start, data=patched)
    sha = hashlib.sha256(garbage).hexdigest()
    path = _with_manifest(real_like, lambda m: m["graphs"]["deform"].update(sha256=sha), tmp_path / "garbage.gtb")
    exc = _runtime_refuses(path)
    assert "graph 'deform'" in _text(exc, path)
    stability.record("bundle", "graph bytes not ONNX (checksum matches)", _observed(exc, path))


HUGE_CLAIMS = {
    "header manifest length 2**50": ("header", 1 << 50),
    "header manifest length 15 MiB (under the cap, past the file)": ("header", 15 << 20),
    "payload_size 2**60": (lambda m: m.update(payload_size=1 << 60), None),
    "buffer shape [2**40, 6] with matching nbytes": (_buffer("pose_track", shape=[1 << 40, 6], nbytes=24 << 40), None),
    "buffer offset 2**62": (_buffer("pose_track", offset=1 << 62), None),
    "buffer shape [2**40, 6], nbytes unchanged": (_buffer("pose_track", shape=[1 << 40, 6]), None),
}


@pytest.mark.parametrize("case", list(HUGE_CLAIMS))
def test_huge_claimed_size_refused_before_allocating(real, tmp_path, stability, case):
    """Refused from the manifest alone: tracemalloc's peak stays under 2 MiB while the claim is >= 15 MiB."""
    edit, length = HUGE_CLAIMS[case]
    if edit == "header":
        data = bytearray(real.data)
        data[16:24] = struct.pack("<Q", length)
        path = tmp_path / "huge.gtb"
        path.write_bytes(bytes(data))
    else:
        path = _with_manifest(real, edit, tmp_path / "huge.gtb")
    for load in (lambda: Bundle(path).verify_all(), lambda: _open_head(path)):
        tracemalloc.start()
        try:
            with pytest.raises(BundleError) as caught:
                load()
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak < 2 << 20, f"{case}: peak {peak} bytes"
    stability.record("bundle", f"huge claim: {case}",
                     f"{_observed(caught.value, path, 70)} (peak alloc {peak / 1024:.0f} KiB)")


# -- checkpoints ------------------------------------------------------------------------------------------------


def _set(*keys_and_value):
    *keys, value = keys_and_value

    def edit(payload):
        target = payload
        for key in keys[:-1]:
            target = target[key]
        target[keys[-1]] = value(target[keys[-1]]) if callable(value) else value
    return edit


def _drop(*keys):
    def edit(payload):
        target = payload
        for key in keys[:-1]:
            target = target[key]
        del target[keys[-1]]
    return edit


CHECKPOINT_CASES = {
    "FLAME v_template missing": (_drop("flame", "v_template"), "missing keys: ['v_template']"),
    "gaussians 'sh' missing": (_drop("gaussians", "sh"), "Missing key(s) in state_dict: \"sh\""),
    "translator weight missing": (lambda p: p["translator"].pop("identity.weight"), "identity.weight"),
    "translator weight wrong shape": (_set("translator", "identity.weight", torch.zeros(3, 3)), "identity.weight"),
    "shape vector wrong length": (_set("shape", torch.zeros(7)), "shape '[20]' is invalid"),
    "pose_track wrong shape [5, 4]": (_set("pose_track", torch.zeros(5, 4)), "'pose_track' has shape [5, 4]"),
    "background of 2 values": (_set("background", [1.0, 1.0]), "'background' must be 3 finite numbers"),
    "float faces": (_set("flame", "faces", lambda t: t.float() + 0.5), "FLAME 'faces' has dtype torch.float32"),
    "float teeth_anchors": (_set("flame", "teeth_anchors", lambda t: t.float()), "FLAME 'teeth_anchors' has dtype"),
    "int64 v_template": (_set("flame", "v_template", lambda t: t.long()), "FLAME 'v_template' has dtype torch.int64"),
    "int64 gaussian log_scale": (_set("gaussians", "log_scale", lambda t: t.long()), "'log_scale' has dtype"),
    "string for FLAME v_template": (_set("flame", "v_template", "v"), "FLAME 'v_template' must be a tensor, got str"),
    "float for a gaussian tensor": (_set("gaussians", "opacity_logit", 0.5), "'opacity_logit' must be a tensor"),
    "string for shape": (_set("shape", "shape"), "'shape' must be a tensor, got str"),
    "list for gaussians": (_set("gaussians", [1, 2]), "'gaussians' must be a dict of tensors, got list"),
    "string for FLAME parents": (_set("flame", "parents", "abc"), "FLAME 'parents' must be a list of ints"),
    "NaN in gaussian sh": (_set("gaussians", "sh", lambda t: t.fill_(float("nan"))), "'sh' contains NaN"),
    "config fps 0": (_set("config", "fps", 0), "config fps must be an int >= 1, got 0"),
    "config fps 30 (the translator makes 25 frames a second)": (
        _set("config", "fps", 30), "sample_rate 16000 / fps 30 = 533.3 samples per video frame, but the translator "
                                   "consumes 640"),
    "config sample rate 8000 (the translator's strides need 16000 at 25 fps)": (
        _set("config", "sample_rate", 8000), "sample_rate 8000 / fps 25 = 320 samples per video frame"),
    "format version 99": (_set("version", 99), "version 99"),
}


@pytest.mark.parametrize("case", list(CHECKPOINT_CASES))
def test_bad_checkpoint_entry(checkpoint, tmp_path, stability, case):
    """Each malformed entry is a CheckpointError naming the entry, raised before any bad value is used."""
    edit, expected = CHECKPOINT_CASES[case]
    payload = copy.deepcopy(checkpoint.payload)
    edit(payload)
    path = tmp_path / "bad.ckpt"
    torch.save(payload, path)
    with pytest.raises(CheckpointError) as caught:
        load_checkpoint(path)
    assert expected in _text(caught.value, path), str(caught.value)
    stability.record("checkpoint", case, _observed(caught.value, path))


@pytest.mark.parametrize("keep", ["0 bytes", "100 bytes", "half", "all but 1 byte"])
def test_truncated_or_empty_checkpoint(checkpoint, tmp_path, stability, keep):
    """A cut-short file is a CheckpointError that says so (torch's zip reader error alone says 'miniz')."""
    data = checkpoint.path.read_bytes()
    size = {"0 bytes": 0, "100 bytes": 100, "half": len(data) // 2, "all but 1 byte": len(data) - 1}[keep]
    path = tmp_path / "cut.ckpt"
    path.write_bytes(data[:size])
    with pytest.raises(CheckpointError) as caught:
        load_checkpoint(path)
    assert re.search(r"is empty \(0 bytes\)|truncated or not a torch.save file", _text(caught.value, path))
    stability.record("checkpoint", f"truncated checkpoint: {keep} kept", _observed(caught.value, path))


class _RunsCode:
    """Unpickling this runs a shell command that creates `marker`."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_legacy_format_pickle_that_would_run_code(tmp_path, stability):
    """A plain (pre-zip) pickle with a code-running payload is refused and nothing runs; the payload is live."""
    marker = tmp_path / "code-ran"
    path = tmp_path / "legacy.ckpt"
    path.write_bytes(pickle.dumps({"format": "gaussiantalker-speaker", "version": 1, "x": _RunsCode(marker)}))
    with pytest.raises(CheckpointError) as caught:
        load_checkpoint(path)
    assert "would run code" in _text(caught.value, path)
    assert not marker.exists()
    pickle.loads(path.read_bytes())  # proof that the payload is not a dud
    assert marker.exists()
    stability.record("checkpoint", "plain pickle (legacy format) that would run os.system",
                     _observed(caught.value, path, 70) + " (nothing ran)")


# -- atomic export ----------------------------------------------------------------------------------------------


class _ShortDisk:
    """A file whose writes fail with `error` once `budget` bytes have gone through."""

    def __init__(self, handle, budget: int, error: BaseException) -> None:
        self.handle, self.budget, self.error = handle, budget, error

    def __getattr__(self, name):
        return getattr(self.handle, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return self.handle.__exit__(*exc)

    def write(self, data) -> int:
        if len(data) > self.budget:
            self.handle.write(data[:self.budget])
            self.handle.flush()
            raise self.error
        self.budget -= len(data)
        return self.handle.write(data)


def _failing_open(budget: int, error: BaseException):
    """`open` for sdk/files.py (the atomic writer) whose files are a _ShortDisk."""

    def failing_open(*args, **kwargs):
        return _ShortDisk(open(*args, **kwargs), budget, error)

    return failing_open


@pytest.mark.parametrize("error", [OSError(28, "No space left on device"), KeyboardInterrupt()],
                         ids=["disk full", "Ctrl-C"])
def test_export_failing_mid_write_keeps_the_good_bundle(real, tmp_path, monkeypatch, stability, error,
                                                         replay_onnx_exports):
    """Half the bundle written, then failure: the good bundle is byte-identical and no temp file is left."""
    out = tmp_path / "speaker.gtb"
    shutil.copy(real.path, out)
    replay_onnx_exports(real.protos)
    monkeypatch.setattr("gaussiantalker.sdk.files.open", _failing_open(len(real.data) // 2, error), raising=False)
    with pytest.raises(type(error)):
        export_bundle(real.speaker, out, progress=False)
    assert out.read_bytes() == real.data
    assert sorted(p.name for p in tmp_path.iterdir()) == ["speaker.gtb"]
    stability.record("export", f"export fails half-way through writing ({type(error).__name__}) over a good bundle",
                     "good bundle byte-identical; temp file removed; nothing else in the folder")


def test_export_failing_between_graphs_writes_nothing(real, tmp_path, monkeypatch, stability):
    """The deform graph's export raises (after the translator's three): nothing at all appears under the output
    name or beside it."""
    protos = iter(real.protos[:3])

    def translator_then_fail(*args, **kwargs):
        for proto in protos:
            return proto
        raise RuntimeError("simulated torch.onnx failure on the deform graph")

    monkeypatch.setattr(onnx_export_module, "export_onnx", translator_then_fail)
    with pytest.raises(RuntimeError, match="simulated"):
        export_bundle(real.speaker, tmp_path / "speaker.gtb", progress=False)
    assert list(tmp_path.iterdir()) == []
    stability.record("export", "export raises between the translator and deform graphs",
                     "RuntimeError propagates; no file created")


_PAUSING_CLI = '''
"""Run gt-export as `python -m gaussiantalker.cli.export` does, pausing once half the bundle is written."""
import os, runpy, sys, time
from pathlib import Path
import onnx
import gaussiantalker.exporter.export.onnx_export as onnx_export
import gaussiantalker.sdk.bundle as bundle
import gaussiantalker.sdk.files as files

graphs, marker, pause_after, *cli_args = sys.argv[1:]
protos = iter([onnx.load_model_from_string(Path(p).read_bytes()) for p in graphs.split(os.pathsep)])
onnx_export.export_onnx = lambda *args, **kwargs: next(protos)


class PausingFile:
    def __init__(self, handle):
        self.handle, self.written = handle, 0
    def __getattr__(self, name):
        return getattr(self.handle, name)
    def __enter__(self):
        return self
    def __exit__(self, *exc):
        return self.handle.__exit__(*exc)
    def write(self, data):
        self.handle.write(data)
        self.written += len(data)
        if self.written >= int(pause_after):
            self.handle.flush()
            Path(marker).touch()
            time.sleep(300)


def pausing_open(*args, **kwargs):
    return PausingFile(open(*args, **kwargs))


bundle.open = files.open = pausing_open  # the bundle writer (staged by gt-export) and the atomic writer
sys.argv = ["gt-export", *cli_args]
runpy.run_module("gaussiantalker.cli.export", run_name="__main__", alter_sys=True)
'''


def _cli_paused_mid_write(real, checkpoint, work: Path, out: Path) -> subprocess.Popen:
    """Start gt-export on the real checkpoint; return once it has written half the bundle and paused."""
    for index, proto in enumerate(real.protos):
        (work / f"graph{index}.onnx").write_bytes(proto.SerializeToString())
    (work / "pausing_cli.py").write_text(_PAUSING_CLI)
    marker = work / "paused"
    graphs = os.pathsep.join(str(work / f"graph{index}.onnx") for index in range(len(real.protos)))
    process = subprocess.Popen([sys.executable, str(work / "pausing_cli.py"), graphs, str(marker),
                                str(len(real.data) // 2),
                                str(checkpoint.path), "-o", str(out), "-q"],
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 120
    while not marker.exists():
        if process.poll() is not None or time.monotonic() > deadline:
            process.kill()
            raise AssertionError(f"gt-export never reached the write: {process.communicate()[0].decode()[-2000:]}")
        time.sleep(0.05)
    return process


@pytest.mark.slow  # a gt-export subprocess paused mid-write, then killed
def test_sigkill_mid_write_leaves_only_a_hidden_tmp_file(real, checkpoint, tmp_path, stability, replay_onnx_exports):
    """SIGKILL half-way through the write: the good bundle is untouched; the one leftover is a hidden *.tmp
    that is not a loadable bundle, and a later export to the same name succeeds."""
    work, out_dir = tmp_path / "work", tmp_path / "out"
    work.mkdir()
    out_dir.mkdir()
    out = out_dir / "speaker.gtb"
    shutil.copy(real.path, out)
    process = _cli_paused_mid_write(real, checkpoint, work, out)
    process.send_signal(signal.SIGKILL)
    process.communicate(timeout=60)
    assert out.read_bytes() == real.data
    leftovers = sorted(p for p in out_dir.iterdir() if p != out)
    assert len(leftovers) == 1 and leftovers[0].name.startswith(".speaker.gtb.") and leftovers[0].suffix == ".tmp"
    assert leftovers[0].stat().st_size < len(real.data)
    exc = _bundle_refuses(leftovers[0])
    replay_onnx_exports(real.protos)
    export_bundle(real.speaker, out, progress=False)
    _open_head(out)
    stability.record("export", "gt-export SIGKILLed half-way through writing, over a good bundle",
                     f"good bundle untouched; left {leftovers[0].name.split('.gtb.')[0]}.gtb.XXXXXXXX.tmp "
                     f"({leftovers[0].stat().st_size} bytes, {_observed(exc, leftovers[0], 40)}); re-export OK")


@pytest.mark.slow  # a gt-export subprocess paused mid-write, then killed
def test_sigterm_mid_write_cleans_up(real, checkpoint, tmp_path, stability):
    """SIGTERM (what `kill` and CI timeouts send) unwinds: the temp file is removed, the good bundle kept."""
    work, out_dir = tmp_path / "work", tmp_path / "out"
    work.mkdir()
    out_dir.mkdir()
    out = out_dir / "speaker.gtb"
    shutil.copy(real.path, out)
    process = _cli_paused_mid_write(real, checkpoint, work, out)
    process.send_signal(signal.SIGTERM)
    process.communicate(timeout=60)
    assert process.returncode == 128 + signal.SIGTERM
    assert out.read_bytes() == real.data
    assert sorted(p.name for p in out_dir.iterdir()) == ["speaker.gtb"]
    stability.record("export", "gt-export SIGTERMed half-way through writing, over a good bundle",
                     f"exit {process.returncode}; good bundle untouched; temp file removed")


def test_failed_verify_keeps_the_real_good_bundle(real, checkpoint, tmp_path, stability, replay_onnx_exports):
    """gt-export --verify that fails: NAME.unverified.gtb holds the new bundle, the good one is untouched."""
    from typer.testing import CliRunner

    from gaussiantalker.cli.export import app

    out = tmp_path / "speaker.gtb"
    shutil.copy(real.path, out)
    replay_onnx_exports(real.protos)
    result = CliRunner().invoke(app, [str(checkpoint.path), "-o", str(out), "--verify", "--frames", "1",
                                      "--resolution", "32", "--min-psnr", "999", "--min-float-psnr", "999", "-q"])
    assert result.exit_code == 1, result.output
    assert "verification FAILED" in result.output
    assert out.read_bytes() == real.data
    assert sorted(p.name for p in tmp_path.iterdir()) == ["speaker.gtb", "speaker.unverified.gtb"]
    Bundle(tmp_path / "speaker.unverified.gtb").verify_all()
    stability.record("export", "gt-export --verify fails (--min-psnr 999) over a real good bundle",
                     "exit 1; good bundle untouched; new one kept as speaker.unverified.gtb; no temp files")
