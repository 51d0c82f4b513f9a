"""Bundle format: round trip, and every kind of damage gives a BundleError that names the problem."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from gaussiantalker.sdk.bundle import FORMAT_MINOR, HEADER_SIZE, MAGIC, Bundle, BundleWriter
from gaussiantalker.sdk.errors import BundleError


def _write(path, codec="raw"):
    writer = BundleWriter({"speaker": {"n_expr": 3}})
    writer.add_buffer("weights", np.arange(24, dtype=np.float32).reshape(4, 6) / 7, codec=codec)
    writer.add_buffer("ids", np.arange(5, dtype=np.int64))
    writer.add_graph("g", b"\x08\x01graph-bytes", [{"name": "x", "dtype": "float32", "shape": [1]}], [],
                     {"w": "weights"})
    writer.write(path)
    return path


def test_round_trip(tmp_path):
    bundle = Bundle(_write(tmp_path / "a.gtb"))
    np.testing.assert_array_equal(bundle.buffer("weights"), np.arange(24, dtype=np.float32).reshape(4, 6) / 7)
    np.testing.assert_array_equal(bundle.buffer("ids"), np.arange(5))
    assert bundle.graph_bytes("g") == b"\x08\x01graph-bytes"
    assert bundle.graph_info("g")["initializers"] == {"w": "weights"}
    assert bundle.version == (1, FORMAT_MINOR)
    bundle.verify_all()


def test_fp16_codec_round_trip_and_overflow(tmp_path):
    bundle = Bundle(_write(tmp_path / "h.gtb", codec="fp16"))
    expected = np.arange(24, dtype=np.float32).reshape(4, 6) / 7
    np.testing.assert_allclose(bundle.buffer("weights"), expected, rtol=1e-3)
    assert bundle.buffer("weights").dtype == np.float32
    writer = BundleWriter()
    with pytest.raises(BundleError, match="fp16 cannot hold"):
        writer.add_buffer("big", np.array([1e6], np.float32), codec="fp16")


def test_truncated_files_are_refused(tmp_path):
    data = _write(tmp_path / "a.gtb").read_bytes()
    for cut in (0, 10, HEADER_SIZE, HEADER_SIZE + 20, len(data) - 1):
        (tmp_path / "t.gtb").write_bytes(data[:cut])
        with pytest.raises(BundleError, match="truncated|not a GaussianTalker"):
            Bundle(tmp_path / "t.gtb")


def test_flipped_payload_byte_names_the_entry(tmp_path):
    path = _write(tmp_path / "a.gtb")
    data = bytearray(path.read_bytes())
    bundle = Bundle(path)
    entry = bundle.manifest["buffers"]["weights"]
    data[bundle.payload_start + entry["offset"] + 3] ^= 0x40
    path.write_bytes(bytes(data))
    damaged = Bundle(path)
    with pytest.raises(BundleError, match="checksum mismatch in buffer 'weights'"):
        damaged.buffer("weights")
    damaged.buffer("ids")  # the undamaged entry still reads


def test_flipped_manifest_byte_is_refused(tmp_path):
    path = _write(tmp_path / "a.gtb")
    data = bytearray(path.read_bytes())
    data[HEADER_SIZE + 5] ^= 0x01
    path.write_bytes(bytes(data))
    with pytest.raises(BundleError, match="manifest checksum"):
        Bundle(path)


def test_unknown_major_version_is_refused(tmp_path):
    path = _write(tmp_path / "a.gtb")
    data = bytearray(path.read_bytes())
    data[8:10] = struct.pack("<H", 2)
    path.write_bytes(bytes(data))
    with pytest.raises(BundleError, match=f"version 2.{FORMAT_MINOR} is not supported"):
        Bundle(path)


def test_not_a_bundle(tmp_path):
    (tmp_path / "x.gtb").write_bytes(b"PK\x03\x04" + b"\0" * 100)
    with pytest.raises(BundleError, match="bad magic"):
        Bundle(tmp_path / "x.gtb")
    with pytest.raises(BundleError, match="does not exist"):
        Bundle(tmp_path / "missing.gtb")


def _rewrite_manifest(path, edit):
    """Re-encode the manifest after `edit(manifest)` with a valid checksum: a well-formed file that lies."""
    import hashlib

    from gaussiantalker.sdk.bundle import _HEADER, _align

    data = path.read_bytes()
    magic, major, minor, reserved, length, _ = _HEADER.unpack_from(data)
    old_start = HEADER_SIZE + _align(length)
    manifest = json.loads(data[HEADER_SIZE: HEADER_SIZE + length])
    edit(manifest)
    raw = json.dumps(manifest).encode()
    header = _HEADER.pack(MAGIC, major, minor, reserved, len(raw), hashlib.sha256(raw).digest())
    header += b"\0" * (HEADER_SIZE - len(header))
    padded = raw + b"\0" * (_align(len(raw)) - len(raw))
    path.write_bytes(header + padded + data[old_start:])


def test_manifest_lying_about_shape_or_dtype(tmp_path):
    path = _write(tmp_path / "a.gtb")
    _rewrite_manifest(path, lambda m: m["buffers"]["weights"].update(shape=[4, 7]))
    with pytest.raises(BundleError, match="buffer 'weights' declares dtype float32 shape \\[4, 7\\]"):
        Bundle(path)
    path = _write(tmp_path / "b.gtb")
    _rewrite_manifest(path, lambda m: m["buffers"]["weights"].update(dtype="float64"))
    with pytest.raises(BundleError, match="unsupported buffer dtype 'float64'"):
        Bundle(path)


def test_huge_claimed_sizes_are_refused_before_reading(tmp_path):
    path = _write(tmp_path / "a.gtb")
    _rewrite_manifest(path, lambda m: m["buffers"]["weights"].update(shape=[1 << 40], nbytes=4 << 40))
    with pytest.raises(BundleError, match="outside the payload"):
        Bundle(path)
    path = _write(tmp_path / "b.gtb")
    data = bytearray(path.read_bytes())
    data[16:24] = struct.pack("<Q", 1 << 50)
    path.write_bytes(bytes(data))
    with pytest.raises(BundleError, match="manifest claims"):
        Bundle(path)


def test_missing_graph_and_buffer_are_named(tmp_path):
    bundle = Bundle(_write(tmp_path / "a.gtb"))
    with pytest.raises(BundleError, match="no graph 'deform'"):
        bundle.graph_bytes("deform")
    with pytest.raises(BundleError, match="no buffer 'nope'"):
        bundle.buffer("nope")
    path = _write(tmp_path / "b.gtb")
    _rewrite_manifest(path, lambda m: m["buffers"].pop("weights"))
    with pytest.raises(BundleError, match="unknown buffer 'weights'"):
        Bundle(path)


def test_write_is_atomic(tmp_path, monkeypatch):
    path = _write(tmp_path / "good.gtb")
    before = path.read_bytes()
    writer = BundleWriter()
    writer.add_buffer("x", np.zeros(3, np.float32))

    def broken_fsync(fd):
        raise OSError("disk full")

    monkeypatch.setattr("os.fsync", broken_fsync)
    with pytest.raises(OSError, match="disk full"):
        writer.write(path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["good.gtb"]


def test_graphs_are_stored_compressed_and_damage_is_named(tmp_path):
    path = _write(tmp_path / "a.gtb")
    entry = Bundle(path).manifest["graphs"]["g"]
    assert entry["compression"] == "zlib" and entry["raw_nbytes"] == len(b"\x08\x01graph-bytes")
    for edit, message in (({"raw_nbytes": 5}, "does not inflate to its declared 5 bytes"),
                          ({"raw_nbytes": 2**40}, "invalid raw_nbytes"),
                          ({"compression": "lzma"}, "unknown compression 'lzma'")):
        writer = BundleWriter({"speaker": {"n_expr": 3}})
        writer.add_buffer("weights", np.zeros(3, np.float32))
        writer.add_graph("g", b"\x08\x01graph-bytes", [], [], {"w": "weights"})
        manifest = writer.manifest()
        manifest["graphs"]["g"].update(edit)
        writer.manifest = lambda manifest=manifest: manifest
        writer.write(tmp_path / "d.gtb")
        with pytest.raises(BundleError, match=message):
            Bundle(tmp_path / "d.gtb").graph_bytes("g")


def _rewrite_manifest_text(path, edit_text):
    """Re-encode the manifest text after `edit_text(text)` with a valid checksum (text-level lies: repeated keys)."""
    import hashlib

    from gaussiantalker.sdk.bundle import _HEADER, _align

    data = path.read_bytes()
    magic, major, minor, reserved, length, _ = _HEADER.unpack_from(data)
    raw = edit_text(data[HEADER_SIZE: HEADER_SIZE + length].decode()).encode()
    header = _HEADER.pack(MAGIC, major, minor, reserved, len(raw), hashlib.sha256(raw).digest())
    header += b"\0" * (HEADER_SIZE - len(header))
    path.write_bytes(header + raw + b"\0" * (_align(len(raw)) - len(raw)) + data[HEADER_SIZE + _align(length):])


def test_manifest_repeating_a_key_is_refused(tmp_path):
    """Two readers could take different values of a repeated key (json keeps the last, others the first)."""
    path = _write(tmp_path / "a.gtb")
    _rewrite_manifest_text(path, lambda text: text[:-1] + ', "payload_size": 0}')
    with pytest.raises(BundleError, match="key 'payload_size' appears twice"):
        Bundle(path)


@pytest.mark.parametrize("constant", ["NaN", "Infinity", "-Infinity"])
def test_manifest_with_a_non_json_number_is_refused(tmp_path, constant):
    """Python's json reads NaN and the infinities; JSON has no such numbers and other readers (the browser's)
    refuse them, so this reader does too; and the writer never writes one."""
    path = _write(tmp_path / "a.gtb")
    _rewrite_manifest_text(path, lambda text: text[:-1] + f', "odd": {constant}}}')
    with pytest.raises(BundleError, match=f"manifest is not valid JSON: {constant} is not a JSON number"):
        Bundle(path)
    writer = BundleWriter(metadata={"odd": float(constant.replace("Infinity", "inf"))})
    with pytest.raises(BundleError, match="cannot write the manifest: .*NaN and infinities are not JSON"):
        writer.write(tmp_path / "b.gtb")
    assert not (tmp_path / "b.gtb").exists()


def test_shape_numpy_cannot_make_is_refused_at_open(tmp_path):
    """An empty buffer claiming a dimension of 2^62 stores 0 bytes, as declared, but no array has that shape."""
    writer = BundleWriter()
    writer.add_buffer("empty", np.zeros((0, 3), np.float32))
    path = tmp_path / "e.gtb"
    writer.write(path)
    Bundle(path).buffer("empty")
    # 2^62 and 10^30 are past 2^53, the largest integer a manifest holds (as JavaScript's readers hold it exactly).
    for shape, why in (([0, 2**62], "malformed dtype, shape or codec"),
                       ([0, 10**30], "malformed dtype, shape or codec"), ([1] * 33, "invalid buffer shape")):
        _rewrite_manifest(path, lambda m, shape=shape: m["buffers"]["empty"].update(shape=shape))
        with pytest.raises(BundleError, match=why):
            Bundle(path)
