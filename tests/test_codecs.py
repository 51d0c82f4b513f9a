"""Buffer codecs: each stated error bound holds, sizes follow from the manifest alone, damage is a BundleError."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from gaussiantalker.sdk.bundle import Bundle, BundleWriter
from gaussiantalker.sdk.codecs import CODECS, encode_buffer, expected_nbytes, get_codec
from gaussiantalker.sdk.errors import BundleError

QUANT_BITS = {"q16": 16, "q8": 8, "q4": 4}


def _round_trip(array: np.ndarray, codec: str, chunk: int | None = None) -> tuple[np.ndarray, dict, int]:
    payload, params = encode_buffer(array, codec, chunk)
    assert expected_nbytes(codec, str(array.dtype), array.shape, params) == len(payload)
    return get_codec(codec).decode(payload, str(array.dtype), array.shape, params), params, len(payload)


def _chunk_bound(array: np.ndarray, bits: int, chunk: int) -> np.ndarray:
    """Per-value error bound of a quantised codec: half a step of the value's chunk (plus float32 rounding)."""
    flat = array.reshape(-1).astype(np.float64)
    bound = np.empty_like(flat)
    for start in range(0, flat.size, chunk):
        block = flat[start:start + chunk]
        half_step = (block.max() - block.min()) / ((1 << bits) - 1) / 2
        bound[start:start + chunk] = half_step * (1 + 1e-6) + np.abs(block) * 2.0 ** -23
    return bound.reshape(array.shape)


@pytest.mark.parametrize("codec", list(QUANT_BITS))
@pytest.mark.parametrize("shape, chunk", [((3, 15, 2001), None), ((7,), 3), ((4, 1000), 1000), ((2, 5), 64)])
def test_quantised_codecs_stay_within_half_a_step(codec, shape, chunk):
    array = (np.random.default_rng(1).normal(size=shape) * np.geomspace(1e-4, 10, shape[-1])).astype(np.float32)
    decoded, params, nbytes = _round_trip(array, codec, chunk)
    bits, used_chunk = QUANT_BITS[codec], params["chunk"]
    assert used_chunk == (chunk or 256)
    assert decoded.dtype == np.float32 and decoded.shape == shape
    assert np.all(np.abs(decoded - array) <= _chunk_bound(array, bits, used_chunk))
    assert nbytes == 8 * -(-array.size // used_chunk) + -(-array.size * bits // 8)


@pytest.mark.parametrize("codec", list(QUANT_BITS))
def test_quantised_codecs_keep_constant_chunks_exact_and_empty_arrays(codec):
    array = np.full((2, 300), 0.1234, np.float32)
    decoded, _, _ = _round_trip(array, codec)
    np.testing.assert_array_equal(decoded, array)
    for empty in (np.zeros((0, 4), np.float32), np.zeros((3, 0), np.float32)):
        assert _round_trip(empty, codec)[0].shape == empty.shape
    assert _round_trip(np.float32(2.5), codec)[0] == np.float32(2.5)


@settings(max_examples=60, deadline=None)
@given(hnp.arrays(np.float32, hnp.array_shapes(min_dims=1, max_dims=3, max_side=40),
                  elements=st.floats(allow_nan=False, allow_infinity=False, width=32)),
       st.sampled_from(list(QUANT_BITS)), st.integers(1, 50))
def test_quantised_codecs_never_decode_to_non_finite(array, codec, chunk):
    decoded, _, _ = _round_trip(array, codec, chunk)
    assert np.all(np.isfinite(decoded))
    assert np.all(np.abs(decoded.astype(np.float64) - array) <= _chunk_bound(array, QUANT_BITS[codec], chunk) + 1e-45)


def test_fp16_and_raw_bounds():
    array = np.random.default_rng(2).normal(size=(50, 7)).astype(np.float32)
    np.testing.assert_array_equal(_round_trip(array, "raw")[0], array)
    assert np.all(np.abs(_round_trip(array, "fp16")[0] - array) <= np.abs(array) * 2.0 ** -11 + 2.0 ** -25)


@pytest.mark.parametrize("high, stored", [(255, "uint8"), (256, "uint16"), (65535, "uint16"), (70000, "uint32")])
def test_index_codec_picks_the_smallest_unsigned_type(high, stored):
    array = np.array([0, 3, high], np.int64)
    decoded, params, nbytes = _round_trip(array, "index")
    np.testing.assert_array_equal(decoded, array)
    assert decoded.dtype == np.int64 and params == {"stored": stored} and nbytes == 3 * np.dtype(stored).itemsize


@pytest.mark.parametrize("array, codec, message", [
    (np.array([-1, 2], np.int64), "index", "non-negative integers only"),
    (np.array([1.5], np.float32), "index", "integer arrays only"),
    (np.array([1, 2], np.int64), "q8", "floating-point arrays only"),
    (np.array([1.0, np.nan], np.float32), "q8", "finite arrays only"),
    (np.array([1.0, np.inf], np.float32), "q4", "finite arrays only"),
])
def test_a_codec_refuses_what_it_cannot_hold(tmp_path, array, codec, message):
    with pytest.raises(BundleError, match=f"buffer 'x': .*{message}"):
        BundleWriter().add_buffer("x", array, codec)


def test_unknown_codec_and_bad_chunk_are_named():
    with pytest.raises(BundleError, match="unknown buffer codec 'q3'.*known: raw, fp16, q16, q8, q4, index"):
        get_codec("q3")
    with pytest.raises(BundleError, match="integer chunk"):
        encode_buffer(np.ones(4, np.float32), "q8", chunk=0)


def _bundle_with(tmp_path, array, codec, edit):
    """A one-buffer bundle whose manifest codec entry is edited (checksums recomputed so only the lie remains)."""
    writer = BundleWriter()
    writer.add_buffer("w", array, codec)
    manifest = writer.manifest()
    edit(manifest["buffers"]["w"])
    writer.manifest = lambda: manifest
    path = tmp_path / "b.gtb"
    writer.write(path)
    return path


@pytest.mark.parametrize("edit, message", [
    (lambda e: e["codec"].update(chunk=0), "buffer 'w': codec 'q8' needs an integer chunk"),
    (lambda e: e["codec"].update(chunk="256"), "buffer 'w': codec 'q8' needs an integer chunk"),
    (lambda e: e["codec"].pop("chunk"), "buffer 'w': codec 'q8' needs an integer chunk"),
    (lambda e: e["codec"].update(chunk=128), "declares dtype float32 shape \\[4, 300\\]"),
    (lambda e: e.update(dtype="int64"), "codec 'q8' cannot decode to dtype 'int64'"),
])
def test_damaged_quantisation_parameters_are_refused_on_open(tmp_path, edit, message):
    path = _bundle_with(tmp_path, np.ones((4, 300), np.float32), "q8", edit)
    with pytest.raises(BundleError, match=message):
        Bundle(path)


def test_damaged_chunk_values_are_refused_on_decode():
    """A chunk minimum or step that is not finite, a negative step, or a range past float32 (written into a payload
    directly: in a bundle the entry's checksum would catch the flipped bytes first)."""
    array = np.linspace(0, 1, 900, dtype=np.float32).reshape(3, 300)  # 4 chunks: 4 minimums, then 4 steps
    payload, params = encode_buffer(array, "q8")
    for offset, damage in ((0, np.nan), (16, np.nan), (16, -1.0), (16, 3e38), (4, -np.inf)):
        broken = bytearray(payload)
        broken[offset:offset + 4] = np.float32(damage).tobytes()
        with pytest.raises(BundleError, match="damaged chunk parameters"):
            get_codec("q8").decode(bytes(broken), "float32", array.shape, params)


def test_index_codec_damaged_stored_type(tmp_path):
    path = _bundle_with(tmp_path, np.arange(10, dtype=np.int64), "index",
                        lambda e: e["codec"].update(stored="uint64"))
    with pytest.raises(BundleError, match="buffer 'w': codec 'index' needs stored in uint8, uint16, uint32"):
        Bundle(path)
    path = _bundle_with(tmp_path, np.arange(300, dtype=np.int64), "index",
                        lambda e: e.update(dtype="uint8", nbytes=e["nbytes"]))
    with pytest.raises(BundleError, match="buffer 'w': codec index: stored value 299 does not fit dtype uint8"):
        Bundle(path).buffer("w")


def test_every_codec_is_documented():
    from gaussiantalker.sdk import codecs

    for name in CODECS:
        assert f"`{name}`" in codecs.__doc__, name


# -- the sparse layer ------------------------------------------------------------------------------------------


def _sparse_array(shape, zeros: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    array = rng.normal(size=shape).astype(np.float32)
    array[rng.random(shape) < zeros] = 0.0
    return array


@pytest.mark.parametrize("codec", ["raw", "fp16", "q16", "q8", "q4"])
@pytest.mark.parametrize("shape, zeros", [((52, 3 * 700), 0.82), ((7,), 0.0), ((9,), 1.0), ((0, 4), 0.5),
                                          ((3, 5, 11), 0.5)])
def test_a_sparse_buffer_decodes_to_its_zeros_and_its_codecs_values(tmp_path, codec, shape, zeros):
    """Zeros stay exact zeros; the nonzero values decode as the codec decodes them alone; the size is the mask plus
    the codec's payload of nnz values, known from the manifest; a bundle round-trips it."""
    array = _sparse_array(shape, zeros)
    payload, params = encode_buffer(array, codec, sparse=True)
    nnz = int(np.count_nonzero(array))
    mask_nbytes = params["sparse"].get("mask_zlib", -(-array.size // 8))  # zlib where that was smaller
    assert params["sparse"] == {"nnz": nnz, **({"mask_zlib": mask_nbytes} if "mask_zlib" in params["sparse"] else {})}
    assert mask_nbytes <= -(-array.size // 8)
    inner = {key: value for key, value in params.items() if key != "sparse"}
    assert len(payload) == mask_nbytes + expected_nbytes(codec, "float32", (nnz,), inner)
    assert expected_nbytes(codec, "float32", shape, params) == len(payload)
    writer = BundleWriter()
    writer.add_buffer("w", array, codec, sparse=True)
    writer.write(tmp_path / "b.gtb")
    decoded = Bundle(tmp_path / "b.gtb").buffer("w")
    assert decoded.shape == array.shape and decoded.dtype == np.float32
    assert np.array_equal(decoded == 0, array == 0)
    alone, _ = encode_buffer(array[array != 0], codec)
    np.testing.assert_array_equal(decoded[array != 0], get_codec(codec).decode(alone, "float32", (nnz,), inner))
    if zeros >= 0.8 and codec == "raw":
        assert len(payload) < 0.25 * array.nbytes  # 18% nonzero: a bit per element and 4 bytes per nonzero


@pytest.mark.parametrize("edit, message", [
    (lambda e: e["codec"].update(sparse={"nnz": -1}), "sparse buffer needs {\"nnz\": K} with 0 <= K <= 40"),
    (lambda e: e["codec"].update(sparse={"nnz": 41}), "sparse buffer needs {\"nnz\": K} with 0 <= K <= 40"),
    (lambda e: e["codec"].update(sparse={"nnz": True}), "sparse buffer needs"),
    (lambda e: e["codec"].update(sparse=[3]), "sparse buffer needs"),
    (lambda e: e["codec"].update(sparse={"nnz": 3, "x": 1}), "sparse buffer needs"),
    (lambda e: e["codec"].update(sparse={"nnz": 2 ** 60}), "sparse buffer needs"),
    (lambda e: e["codec"].update(sparse={"nnz": 20}), "declares dtype float32 shape \\[4, 10\\]"),
])
def test_a_damaged_sparse_entry_is_refused_on_open(tmp_path, edit, message):
    writer = BundleWriter()
    writer.add_buffer("w", _sparse_array((4, 10), 0.7), "raw", sparse=True)
    manifest = writer.manifest()
    edit(manifest["buffers"]["w"])
    writer.manifest = lambda: manifest
    writer.write(tmp_path / "b.gtb")
    with pytest.raises(BundleError, match=message):
        Bundle(tmp_path / "b.gtb")


def _runs_array(seed: int = 3) -> np.ndarray:
    """A morph basis in miniature: 12 shapes, each moving one run of 300-900 of 6,000 coordinates."""
    rng = np.random.default_rng(seed)
    array = np.zeros((12, 6000), np.float32)
    for row in array:
        start = int(rng.integers(0, 5000))
        row[start: start + int(rng.integers(300, 900))] = rng.normal(size=1) * 1e-3 + 1e-4
    return array


@pytest.mark.parametrize("codec", ["raw", "q8"])
def test_a_mask_in_runs_is_stored_deflated_and_decodes_exactly(tmp_path, codec):
    """A mask of long runs (a morph basis: one region per shape) is stored as its zlib stream, far smaller than the
    bitmask, and a bundle round-trips it; the manifest alone still says the stored size."""
    array = _runs_array()
    payload, params = encode_buffer(array, codec, sparse=True)
    bitmask = -(-array.size // 8)
    assert 0 < params["sparse"]["mask_zlib"] < bitmask / 20
    assert expected_nbytes(codec, "float32", array.shape, params) == len(payload)
    writer = BundleWriter()
    writer.add_buffer("w", array, codec, sparse=True)
    writer.write(tmp_path / "b.gtb")
    decoded = Bundle(tmp_path / "b.gtb").buffer("w")
    assert np.array_equal(decoded == 0, array == 0)
    if codec == "raw":
        np.testing.assert_array_equal(decoded, array)


def _deflated(mask_bytes: bytes) -> bytes:
    import zlib

    return zlib.compress(mask_bytes, 9)


@pytest.mark.parametrize("damage, message", [
    (lambda z, m: z[:-1], "does not inflate to exactly|damaged"),  # cut short: checksum incomplete
    (lambda z, m: z[:2] + bytes([z[2] ^ 0xFF]) + z[3:], "damaged|does not inflate"),  # a flipped DEFLATE byte
    (lambda z, m: z[:-4] + bytes(4), "damaged"),  # a wrong checksum
    (lambda z, m: _deflated(m + b"\0"), "does not inflate to exactly its 9000 bytes"),  # a longer mask
    (lambda z, m: _deflated(m[:-1]), "does not inflate to exactly its 9000 bytes"),  # a shorter one
    (lambda z, m: z + b"\0", "does not inflate to exactly"),  # bytes after the stream
    (lambda z, m: _deflated(bytes(10 ** 6)), "does not inflate to exactly its 9000 bytes"),  # a zip bomb, bounded
])
def test_a_damaged_deflated_mask_is_refused_on_decode(damage, message):
    """Every way a zlib mask can be wrong is a BundleError that names it (payloads edited directly, with the
    manifest's `mask_zlib` following them: in a bundle the checksum would catch the bytes first)."""
    from gaussiantalker.sdk.codecs import decode_buffer

    array = _runs_array()
    payload, params = encode_buffer(array, "raw", sparse=True)
    stored = params["sparse"]["mask_zlib"]
    mask = np.packbits(array.reshape(-1) != 0, bitorder="little").tobytes()
    assert len(mask) == 9000 and _deflated(mask) == payload[:stored]  # 72,000 elements: 9,000 bytes
    damaged = damage(payload[:stored], mask)
    edited = {**params, "sparse": {**params["sparse"], "mask_zlib": len(damaged)}}
    with pytest.raises(BundleError, match=message):
        decode_buffer(damaged + payload[stored:], "raw", "float32", array.shape, edited)


@pytest.mark.parametrize("zipped", [-1, True, 1.5, "10", 9000 + 5 + 6 + 1])
def test_a_mask_size_the_mask_cannot_have_is_refused_from_the_manifest(zipped):
    """`mask_zlib` is a whole number no larger than zlib's stored-block bound of the mask (9,011 bytes here)."""
    with pytest.raises(BundleError, match="optionally \"mask_zlib\": M, at most 9011 bytes"):
        expected_nbytes("raw", "float32", (12, 6000), {"sparse": {"nnz": 10, "mask_zlib": zipped}})


def test_a_sparse_mask_that_disagrees_with_nnz_is_refused_on_decode():
    """The mask's set bits must number nnz, and its spare bits past the last element must be zero (payloads edited
    directly: in a bundle the entry's checksum would catch the flipped bytes first)."""
    from gaussiantalker.sdk.codecs import decode_buffer

    array = np.array([1, 0, 2, 0, 0, 3, 0, 0, 0, 0, 0, 0, 4], np.float32)
    payload, params = encode_buffer(array, "raw", sparse=True)
    assert payload[:2] == bytes([0b00100101, 0b00010000]) and params["sparse"] == {"nnz": 4}
    extra = bytearray(payload)
    extra[0] |= 0b10  # element 1 marked nonzero: 5 set bits for 4 values
    with pytest.raises(BundleError, match="mask marks 5 nonzero elements, its nnz says 4"):
        decode_buffer(bytes(extra), "raw", "float32", (13,), params)
    spare = bytearray(payload)
    spare[1] |= 0x80  # bit 15: past element 12
    with pytest.raises(BundleError, match="bits set past its last element"):
        decode_buffer(bytes(spare), "raw", "float32", (13,), params)
