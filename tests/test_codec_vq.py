"""The `vq` (codebook) codec and buffers stored zlib-compressed (format 1.3): sizes follow from the manifest alone,
what is decoded is the codebook's nearest entry, k-means is deterministic, and every damage is a BundleError."""

from __future__ import annotations

import zlib

import numpy as np
import pytest

from gaussiantalker.sdk.bundle import Bundle, BundleWriter
from gaussiantalker.sdk.codecs import decode_buffer, encode_buffer, expected_nbytes, index_bits
from gaussiantalker.sdk.errors import BundleError
from gaussiantalker.sdk.kmeans import kmeans


def _clusters(k: int, n: int, width: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """[width, n] vectors scattered tightly around k well-apart centres, and each one's centre id."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-4, 4, size=(k, width))
    labels = rng.integers(k, size=n)
    values = centres[labels] + rng.normal(scale=1e-3, size=(n, width))
    return values.T.astype(np.float32), labels


@pytest.mark.parametrize("entries, bits", [(1, 1), (2, 1), (3, 2), (12, 4), (256, 8), (300, 9), (65536, 16)])
def test_index_bits(entries, bits):
    assert index_bits(entries) == bits


@pytest.mark.parametrize("shape, entries", [((3, 500), 12), ((4, 2000), 256), ((700,), 5), ((2, 3, 400), 300)])
def test_a_codebook_finds_clustered_vectors_and_its_size_is_the_manifests(shape, entries):
    """Vectors around `entries` centres decode to within the clusters' spread plus float16 rounding, and the payload
    has exactly the bytes the manifest implies (2 K D + ceil(N b / 8))."""
    width, n = int(np.prod(shape[:-1])), shape[-1]
    vectors, _ = _clusters(min(entries, 60), n, width)
    array = vectors.reshape(shape)
    payload, params = encode_buffer(array, "vq", entries)
    k = params["entries"]
    assert k == min(entries, n)
    assert len(payload) == expected_nbytes("vq", "float32", shape, params) == 2 * k * width + -(-n * index_bits(k) // 8)
    decoded = decode_buffer(payload, "vq", "float32", shape, params)
    assert decoded.shape == shape and decoded.dtype == np.float32
    assert np.abs(decoded - array).max() <= 5e-3 + 4 * 2.0 ** -11 * 4  # the spread, plus a half-float step at 4
    rows = decoded.reshape(width, n).T
    assert len(np.unique(rows, axis=0)) <= k  # every vector is one of the codebook's entries


def test_a_codebook_is_deterministic_and_each_vector_takes_its_nearest_stored_entry():
    rng = np.random.default_rng(5)
    array = rng.normal(size=(3, 3000)).astype(np.float32)
    first = encode_buffer(array, "vq", 64)
    assert encode_buffer(array, "vq", 64) == first
    payload, params = first
    table = np.frombuffer(payload, "<f2", 64 * 3).reshape(64, 3).astype(np.float64)
    decoded = decode_buffer(payload, "vq", "float32", array.shape, params).astype(np.float64)
    nearest = ((array.T[:, None, :] - table[None]) ** 2).sum(-1).min(1)
    np.testing.assert_allclose(((array.T - decoded.T) ** 2).sum(1), nearest, rtol=1e-9, atol=1e-12)


def test_kmeans_recovers_separated_clusters():
    vectors, labels = _clusters(8, 4000, 3, seed=2)
    centres, index = kmeans(vectors.T, 8)
    # the same partition up to the clusters' numbering
    pairs = set(zip(labels.tolist(), index.tolist(), strict=True))
    assert len(pairs) == 8


@pytest.mark.parametrize("shape", [(3, 0), (0,), (0, 5)])
def test_an_empty_array_round_trips(shape):
    array = np.zeros(shape, np.float32)
    payload, params = encode_buffer(array, "vq", 16)
    assert len(payload) == expected_nbytes("vq", "float32", shape, params)
    assert decode_buffer(payload, "vq", "float32", shape, params).shape == shape


def test_a_sparse_codebook_keeps_its_zeros():
    rng = np.random.default_rng(1)
    array = np.where(rng.random((6, 400)) < 0.8, 0.0, rng.normal(size=(6, 400))).astype(np.float32)
    payload, params = encode_buffer(array, "vq", 16, sparse=True)
    decoded = decode_buffer(payload, "vq", "float32", array.shape, params)
    np.testing.assert_array_equal(decoded == 0, array == 0)


@pytest.mark.parametrize("array, message", [
    (np.array([1, 2], np.int64), "floating-point arrays only"),
    (np.array([1.0, np.nan], np.float32), "finite arrays within float16's range"),
    (np.array([1.0, 1e6], np.float32), "finite arrays within float16's range"),
])
def test_vq_refuses_what_it_cannot_hold(array, message):
    with pytest.raises(BundleError, match=f"buffer 'x': .*{message}"):
        BundleWriter().add_buffer("x", array, "vq")


@pytest.mark.parametrize("params", [{}, {"entries": 0}, {"entries": 65537}, {"entries": "8"}, {"entries": True}])
def test_a_bad_entries_parameter_is_named(params):
    with pytest.raises(BundleError, match="codec 'vq' needs an integer entries in 1..65536"):
        expected_nbytes("vq", "float32", (3, 10), params)


def test_vq_decodes_to_floats_only():
    with pytest.raises(BundleError, match="cannot decode to dtype 'int32'"):
        expected_nbytes("vq", "int32", (3, 10), {"entries": 4})


def _payload_with_indices(table: np.ndarray, indices: list[int], bits: int, extra_bit: int | None = None) -> bytes:
    stream = np.zeros(-(-len(indices) * bits // 8) * 8, np.uint8)
    for n, index in enumerate(indices):
        stream[n * bits:(n + 1) * bits] = (index >> np.arange(bits)) & 1
    if extra_bit is not None:
        stream[extra_bit] = 1
    return table.astype("<f2").tobytes() + np.packbits(stream, bitorder="little").tobytes()


def test_damaged_codebooks_are_refused_on_decode():
    """A codebook value that is not finite, an index past the codebook and a bit set past the last index (payloads
    written directly: in a bundle the checksum would catch the bytes first)."""
    table = np.array([[0.5, 1.0], [2.0, -1.0], [3.0, 0.0]])  # K = 3, D = 2: 2-bit indices
    params = {"entries": 3}
    good = _payload_with_indices(table, [0, 2, 1], 2)
    np.testing.assert_array_equal(decode_buffer(good, "vq", "float32", (2, 3), params),
                                  np.array([[0.5, 3.0, 2.0], [1.0, 0.0, -1.0]], np.float32))
    with pytest.raises(BundleError, match="index 3 past the codebook's 3 entries"):
        decode_buffer(_payload_with_indices(table, [0, 3, 1], 2), "vq", "float32", (2, 3), params)
    with pytest.raises(BundleError, match="bits are set past the last index"):
        decode_buffer(_payload_with_indices(table, [0, 2, 1], 2, extra_bit=7), "vq", "float32", (2, 3), params)
    for bad in (np.inf, np.nan):
        broken = table.copy()
        broken[1, 0] = bad
        with pytest.raises(BundleError, match="codebook holds a value that is not finite"):
            decode_buffer(_payload_with_indices(broken, [0, 2, 1], 2), "vq", "float32", (2, 3), params)


# -- buffers stored zlib-compressed -----------------------------------------------------------------------------


def _runs() -> np.ndarray:
    array = np.zeros((8, 3000), np.float32)
    for row in range(8):
        array[row, 300 * row: 300 * row + 500] = np.linspace(-1, 1, 500)
    return array


def test_a_compressed_buffer_is_stored_smaller_and_decodes_as_the_uncompressed_one(tmp_path):
    array = _runs()
    writer = BundleWriter()
    writer.add_buffer("plain", array, "q8", 64)
    writer.add_buffer("zipped", array, "q8", 64, compress=True)
    writer.add_buffer("noise", np.random.default_rng(0).integers(0, 256, 4000, np.uint8), compress=True)
    writer.write(tmp_path / "b.gtb")
    bundle = Bundle(tmp_path / "b.gtb")
    entries = bundle.manifest["buffers"]
    assert entries["zipped"]["compression"] == "zlib"
    assert entries["zipped"]["raw_nbytes"] == entries["plain"]["nbytes"] > 4 * entries["zipped"]["nbytes"]
    assert "compression" not in entries["noise"]  # random bytes do not deflate: stored as they are
    np.testing.assert_array_equal(bundle.buffer("zipped"), bundle.buffer("plain"))
    np.testing.assert_array_equal(writer.decoded_buffer("zipped"), bundle.buffer("plain"))


def _compressed_bundle(tmp_path, edit=lambda entry, stream: stream):
    """A bundle whose one compressed buffer's stream and entry are edited (checksums made to match)."""
    writer = BundleWriter()
    writer.add_buffer("w", _runs(), "q8", 64, compress=True)
    manifest = writer.manifest()
    entry = manifest["buffers"]["w"]
    stream = edit(entry, zlib.compress(writer._stored["w"], 9))
    rewritten = BundleWriter()
    rewritten._append(stream)
    import hashlib

    entry.update(nbytes=len(stream), sha256=hashlib.sha256(stream).hexdigest())
    manifest["payload_size"] = -(-len(stream) // 64) * 64
    rewritten.manifest = lambda: manifest
    rewritten.write(tmp_path / "d.gtb")
    return tmp_path / "d.gtb"


@pytest.mark.parametrize("edit, message", [
    (lambda e, s: (e.update(compression="lzma"), s)[1], "unknown compression 'lzma'"),
    (lambda e, s: (e.update(raw_nbytes=2**40), s)[1], "invalid raw_nbytes"),
    (lambda e, s: (e.pop("raw_nbytes"), s)[1], "invalid raw_nbytes"),
    (lambda e, s: (e.update(raw_nbytes=e["raw_nbytes"] + 1), s)[1], "its stream's raw_nbytes is"),
    (lambda e, s: bytes(e["raw_nbytes"] + 100), "at most"),  # more bytes than zlib's bound for the buffer
])
def test_a_compressed_buffer_entry_that_cannot_be_is_refused_on_open(tmp_path, edit, message):
    with pytest.raises(BundleError, match=f"buffer 'w'.*{message}"):
        Bundle(_compressed_bundle(tmp_path, edit))


@pytest.mark.parametrize("edit, message", [
    (lambda e, s: s[:-1], "does not inflate"),  # cut short
    (lambda e, s: s[:-4] + bytes(4), "does not inflate"),  # a wrong checksum
    (lambda e, s: s + b"\0", "does not inflate"),  # bytes after the stream
    (lambda e, s: zlib.compress(bytes(e["raw_nbytes"] - 1), 9), "does not inflate to its declared"),  # shorter
    (lambda e, s: zlib.compress(bytes(10**6), 9), "does not inflate to its declared"),  # a bomb, bounded
])
def test_a_damaged_compressed_buffer_is_refused_on_read(tmp_path, edit, message):
    bundle = Bundle(_compressed_bundle(tmp_path, edit))
    with pytest.raises(BundleError, match=f"buffer 'w' {message}"):
        bundle.buffer("w")


@pytest.mark.parametrize("raw", [0, 5])
def test_inflating_stops_one_byte_past_the_declared_size(monkeypatch, raw):
    """A stream that inflates past raw_nbytes is refused after at most one byte more, also when raw_nbytes is 0
    (zlib's own max_length of 0 would mean no bound at all). The inflater's output is recorded as it is made."""
    import gaussiantalker.sdk.bundle as bundle_module

    produced, original = [], zlib.decompressobj

    class Recording:
        def __init__(self):
            self.inner = original()

        def decompress(self, data, max_length=0):
            out = self.inner.decompress(data, max_length)
            produced.append(len(out))
            return out

        def __getattr__(self, name):
            return getattr(self.inner, name)

    monkeypatch.setattr(bundle_module.zlib, "decompressobj", Recording)
    reader = Bundle.__new__(Bundle)
    reader.path = "bomb.gtb"
    with pytest.raises(BundleError, match=f"does not inflate to its declared {raw} bytes"):
        reader._inflate("graph 'g'", zlib.compress(bytes(10**7), 9), raw)
    assert sum(produced) <= raw + 1
