"""The browser player's readers of a user's bytes, run by node on seeded mutations: the bundle reader
(web/src/bundle.js) on the Python reader's bundle cases (tests/test_fuzz_readers.py: header fields set to 0/-1/huge,
bytes mutated anywhere, manifest values swapped under a matching digest), the motion file reader (web/src/drive.js)
on LAM motion JSON, the FLAME motion reader (web/src/flame_motion.js over npz.js) on GaussianAvatars' npz, and the
live drive decoder (web/src/live.js) on drive messages. Every case either loads or is
refused with the reader's own error (one line; naming the file where there is one), never another exception or a
hang, and each JS reader's verdict is its Python twin's, case by case (docs/web.md, "Rejections").

Needs node (.ci/browser's npm brings it in CI, where this test fails without it)."""

from __future__ import annotations

import json
import shutil
import struct
import subprocess
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from ci_tools import BROWSER_INSTALL, need
from fuzz_mutations import dumps, mutate_bytes, mutate_field_bytes
from test_fuzz_readers import (  # noqa: F401  (small_bundle: a fixture)
    _bundle_with_manifest,
    bundle_manifest,
    motion_documents,
    mutated_bundle,
    mutated_motion,
    small_bundle,
)

from gaussiantalker.sdk.bundle import MAX_MANIFEST_DEPTH, Bundle
from gaussiantalker.sdk.errors import BundleError

ROOT = Path(__file__).resolve().parents[1]
CASES = {"ci": 300, "heavy": 3000}
# Seconds the node process may take for all cases (each is a few kB; the CI run takes about a second).
NODE_TIMEOUT_S = 300

# -- the JS readers run by node, and their verdicts against Python's -------------------------------------------

READERS = """
import fs from 'node:fs';
import { readBundle, BundleError } from %(bundle_js)s;
import { readMotion, motionAtFps, DriveError } from %(drive_js)s;
import { decodeDrive, DriveFormatError } from %(live_js)s;
const { kind, paths } = JSON.parse(fs.readFileSync(%(list)s, 'utf8'));
// The bundle reader (its deflated sparse masks) and the FLAME motion reader need the npm install (fflate
// inflates); the other readers run on node alone.
const { flameMotionAtFps, readFlameMotion } = kind === 'flame_motion' ? await import(%(flame_motion_js)s) : {};
const read = {
  bundle: async (path) => {
    const bundle = await readBundle(fs.readFileSync(path), { name: path });
    for (const name of Object.keys(bundle.manifest.buffers)) bundle.buffer(name);
    for (const name of bundle.graphNames()) await bundle.graphBytes(name);
  },
  motion: (path) => motionAtFps(readMotion(fs.readFileSync(path), path), 30),
  flame_motion: (path) => flameMotionAtFps(readFlameMotion(fs.readFileSync(path), 25, path), 30),
  drive: (path) => decodeDrive(fs.readFileSync(path)),
};
const refusal = { bundle: BundleError, motion: DriveError, flame_motion: DriveError, drive: DriveFormatError };
const results = [];
for (const path of paths) {
  try {
    await read[kind](path);
    results.push({ verdict: 'loaded' });
  } catch (error) {
    results.push({ verdict: error instanceof refusal[kind] ? 'refused' : 'crashed',
                   message: `${error?.constructor?.name}: ${error?.message}` });
  }
}
console.log(JSON.stringify(results));
"""


def _web_verdicts(kind: str, paths: list[Path], folder: Path) -> list[dict]:
    """What the JS reader of `kind` ("bundle", "motion", "flame_motion" or "drive") says of each file."""
    node = shutil.which("node")
    need(None if node else "node is missing (Debian's npm brings it)", BROWSER_INSTALL)
    if kind == "flame_motion":
        from tools.browser.web_harness import NPM_MODULES

        fflate = ROOT / "web" / NPM_MODULES["fflate"]
        need(None if fflate.is_file() else f"fflate is not installed in {ROOT / 'web' / 'node_modules'}: run `npm ci` "
             "in web/", BROWSER_INSTALL)
    listing = folder / "cases.json"
    listing.write_text(json.dumps({"kind": kind, "paths": [str(path) for path in paths]}))
    script = folder / "readers.mjs"
    script.write_text(READERS % {"bundle_js": json.dumps((ROOT / "web" / "src" / "bundle.js").as_uri()),
                                 "drive_js": json.dumps((ROOT / "web" / "src" / "drive.js").as_uri()),
                                 "live_js": json.dumps((ROOT / "web" / "src" / "live.js").as_uri()),
                                 "flame_motion_js": json.dumps((ROOT / "web" / "src" / "flame_motion.js").as_uri()),
                                 "list": json.dumps(str(listing))})
    done = subprocess.run([node, str(script)], capture_output=True, text=True, timeout=NODE_TIMEOUT_S)
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout)


def _check_verdicts(kind: str, cases: list[tuple[Path, str]], read_in_python, error: type[Exception], folder: Path,
                    names_file: bool = True) -> list[dict]:
    """Run the JS reader of `kind` on every case: each must agree with `read_in_python(path)` (loaded, or refused
    with `error`) and refuse in one line. Returns the JS results."""

    def python_verdict(path: Path) -> str:
        try:
            read_in_python(path)
        except error:
            return "refused"
        return "loaded"

    web = _web_verdicts(kind, [path for path, _ in cases], folder)
    problems = _disagreements(cases, web, python_verdict, names_file)
    assert not problems, "\n".join(problems[:20]) + f"\n({len(problems)} in all)"
    return web


def _disagreements(cases: list[tuple[Path, str]], web: list[dict], python_verdict, names_file: bool) -> list[str]:
    """Every case where the JS reader crashed, wrote a bad message, or disagreed with Python."""
    problems = []
    for (path, what), result in zip(cases, web, strict=True):
        where = f"{path.name} ({what})"
        if result["verdict"] == "crashed":
            problems.append(f"{where}: not the reader's error: {result['message'][:300]}")
            continue
        message = result.get("message", "")
        if result["verdict"] == "refused" and ("\n" in message or (names_file and str(path) not in message)):
            problems.append(f"{where}: the message is not one line naming the file: {message[:300]!r}")
        python = python_verdict(path)
        if python != result["verdict"]:
            problems.append(f"{where}: Python {python}, web {result['verdict']} ({message[:200]})")
    return problems


# -- bundles --------------------------------------------------------------------------------------------------------


def _python_verdict(path: Path) -> str:
    """What the Python reader says of a file, read as tests/test_fuzz_readers.py reads it."""
    try:
        bundle = Bundle(path)
        bundle.verify_all()
        for name in bundle.manifest["buffers"]:
            bundle.buffer(name)
        for name in bundle.manifest["graphs"]:
            bundle.graph_bytes(name)
    except BundleError:
        return "refused"
    return "loaded"


def _cases(data: bytes, folder: Path, count: int, seed: int) -> list[tuple[Path, str]]:
    """(file, what was done) for `count` seeded mutations of the bundle `data`, as the Python fuzz makes them."""
    manifest = bundle_manifest(data)
    rng = np.random.default_rng(seed)
    cases = []
    for index in range(count):
        mutated, what = mutated_bundle(data, manifest, rng)
        path = folder / f"case{index:05d}.gtb"
        path.write_bytes(mutated)
        cases.append((path, what))
    for depth in (MAX_MANIFEST_DEPTH, MAX_MANIFEST_DEPTH + 1):  # either side of the nesting bound
        path = folder / f"depth{depth}.gtb"
        path.write_bytes(_bundle_with_manifest(data, dumps({**manifest, "note": _nested(depth - 1)})))
        cases.append((path, f"a manifest {depth} deep"))
    return cases


def _nested(levels: int) -> object:
    """A value that is `levels` arrays deep."""
    value: object = 0
    for _ in range(levels):
        value = [value]
    return value


@pytest.mark.parametrize("run, seed", [pytest.param("ci", 0, id="ci"),
                                       pytest.param("heavy", 1000, id="heavy", marks=pytest.mark.heavy)])
def test_fuzz_the_web_bundle_reader(small_bundle, tmp_path, run, seed):  # noqa: F811  (the imported fixture)
    cases = _cases(small_bundle, tmp_path, CASES[run], seed + 9)
    web = _web_verdicts("bundle", [path for path, _ in cases], tmp_path)
    problems = _disagreements(cases, web, _python_verdict, names_file=True)
    assert not problems, "\n".join(problems[:20]) + f"\n({len(problems)} in all)"
    verdicts = {verdict: sum(r["verdict"] == verdict for r in web) for verdict in ("loaded", "refused")}
    assert verdicts["refused"] > len(cases) // 2 and verdicts["loaded"] > 0, verdicts  # the cases reach both ends


def test_a_manifest_nesting_past_the_bound_is_refused(small_bundle, tmp_path):  # noqa: F811
    """One level past MAX_MANIFEST_DEPTH is refused by the Python reader (the JS one: the fuzz's last two cases);
    the bound itself loads."""
    manifest = bundle_manifest(small_bundle)
    for depth, verdict in ((MAX_MANIFEST_DEPTH, "loaded"), (MAX_MANIFEST_DEPTH + 1, "refused")):
        path = tmp_path / f"depth{depth}.gtb"  # the manifest itself is level 1
        path.write_bytes(_bundle_with_manifest(small_bundle, dumps({**manifest, "note": _nested(depth - 1)})))
        assert _python_verdict(path) == verdict, depth
    with pytest.raises(BundleError, match="manifest is not valid JSON: it nests too deep"):
        Bundle(path)


# -- motion files and live drive messages ----------------------------------------------------------------------


@pytest.mark.parametrize("run, seed", [pytest.param("ci", 0, id="ci"),
                                       pytest.param("heavy", 1000, id="heavy", marks=pytest.mark.heavy)])
def test_fuzz_the_web_motion_reader(tmp_path, run, seed):
    """LAM motion JSON (the documents tests/test_fuzz_readers.py mutates) through `readMotion` and `motionAtFps`
    against `runtime.motions.arkit_motion` at 30 fps."""
    from gaussiantalker.runtime.motions import arkit_motion
    from gaussiantalker.sdk.errors import DriveError

    documents = motion_documents()
    rng = np.random.default_rng(seed + 7)
    cases = []
    for index in range(CASES[run]):
        data, what = mutated_motion(documents[index % len(documents)], rng)
        path = tmp_path / f"motion{index:05d}.json"
        path.write_bytes(data)
        cases.append((path, what))

    web = _check_verdicts("motion", cases, lambda path: arkit_motion(path, None, 30, "speaker"), DriveError, tmp_path)
    assert sum(r["verdict"] == "loaded" for r in web) > 0


def _flame_params(frames: int = 4, n_expr: int = 10) -> dict[str, np.ndarray]:
    """A small flame_param.npz's arrays, GaussianAvatars' keys and dtypes: the motion's per-frame keys and per-avatar
    ones the motion reader skips."""
    rng = np.random.default_rng(5)
    per_frame = {"expr": n_expr, "rotation": 3, "neck_pose": 3, "jaw_pose": 3, "eyes_pose": 6, "translation": 3}
    params = {key: (0.2 * rng.standard_normal((frames, width))).astype(np.float32) for key, width in per_frame.items()}
    params["shape"] = rng.standard_normal(300).astype(np.float32)
    params["static_offset"] = np.zeros((1, 40, 3), np.float32)
    params["timestep_index"] = np.arange(frames)
    return params


@pytest.mark.parametrize("run, seed", [pytest.param("ci", 0, id="ci"),
                                       pytest.param("heavy", 1000, id="heavy", marks=pytest.mark.heavy)])
def test_fuzz_the_web_flame_motion_reader(tmp_path, run, seed):
    """GaussianAvatars' flame_param.npz (arrays reshaped, retyped, pickled, headers lying; zip header fields; bytes;
    stored and deflated) through `readFlameMotion` (web/src/npz.js, npy_header.js, flame_motion.js) and
    `flameMotionAtFps` against `load_flame_motion(...).at_fps(30)`, case by case."""
    from fuzz_mutations import mutate_npz_arrays, mutate_zip_field, npz_bytes

    from gaussiantalker.sdk.errors import DriveError
    from gaussiantalker.sdk.flame_motion import load_flame_motion

    params = _flame_params()
    rng = np.random.default_rng(seed + 13)
    cases = []
    for index in range(CASES[run]):
        choice, compressed = rng.random(), bool(index % 2)
        if choice < 0.45:
            data, what = mutate_npz_arrays(params, rng)
        elif choice < 0.75:
            data, what = mutate_zip_field(npz_bytes(params, compressed), rng)
        elif choice < 0.97:
            data, what = mutate_bytes(npz_bytes(params, compressed), rng)
        else:
            data, what = npz_bytes(params, compressed), "valid"
        path = tmp_path / f"flame{index:05d}.npz"
        path.write_bytes(data)
        cases.append((path, what + (" (deflated)" if compressed else "")))

    web = _check_verdicts("flame_motion", cases, lambda path: load_flame_motion(path, 25).at_fps(30), DriveError,
                          tmp_path)
    loaded = sum(r["verdict"] == "loaded" for r in web)
    assert 0 < loaded < len(cases), loaded  # the cases reach both ends


def test_the_web_reader_decodes_and_refuses_deflated_masks_as_python_does(tmp_path):
    """`decodeBuffer` (web/src/codecs.js) against sdk/codecs.py `decode_buffer` on a sparse buffer whose mask is
    stored deflated, intact and damaged every way tests/test_codecs.py damages it, plus seeded byte flips and cuts
    of the stream: the same values where Python decodes, refused where Python refuses (with the manifest's
    `mask_zlib` following each payload, as a bundle's checksum would otherwise catch the bytes first)."""
    import base64
    import zlib

    from test_codecs import _runs_array

    from gaussiantalker.sdk.codecs import decode_buffer, encode_buffer

    node = shutil.which("node")
    need(None if node else "node is missing (Debian's npm brings it)", BROWSER_INSTALL)
    array = _runs_array()
    payload, params = encode_buffer(array, "q8", 16, sparse=True)
    stored = params["sparse"]["mask_zlib"]
    stream, values = payload[:stored], payload[stored:]
    mask = np.packbits(array.reshape(-1) != 0, bitorder="little").tobytes()
    rng = np.random.default_rng(0)
    streams = [stream, stream[:-1], stream[:-4] + bytes(4), stream + b"\0", zlib.compress(mask + b"\0"),
               zlib.compress(mask[:-1]), zlib.compress(bytes(10 ** 6)), b"", stream[:2]]
    for _ in range(60):
        damaged = bytearray(stream)
        if rng.random() < 0.5:
            damaged[rng.integers(len(damaged))] ^= 1 << int(rng.integers(8))
        else:
            damaged = damaged[: rng.integers(len(damaged))]
        streams.append(bytes(damaged))
    cases = []
    for data in streams:
        case_params = {**params, "sparse": {**params["sparse"], "mask_zlib": len(data)}}
        try:
            want = decode_buffer(data + values, "q8", "float32", array.shape, case_params).tobytes()
        except BundleError:
            want = None
        cases.append({"payload": base64.b64encode(data + values).decode(), "params": case_params,
                      "want": None if want is None else base64.b64encode(want).decode()})
    (tmp_path / "cases.json").write_text(json.dumps({"shape": list(array.shape), "cases": cases}))
    script = tmp_path / "masks.mjs"
    script.write_text(f"""
import fs from 'node:fs';
import {{ BundleError, decodeBuffer }} from {json.dumps((ROOT / "web" / "src" / "codecs.js").as_uri())};
const {{ shape, cases }} = JSON.parse(fs.readFileSync({json.dumps(str(tmp_path / "cases.json"))}, 'utf8'));
console.log(JSON.stringify(cases.map(({{ payload, params }}) => {{
  try {{
    const values = decodeBuffer(new Uint8Array(Buffer.from(payload, 'base64')), 'q8', 'float32', shape, params);
    return Buffer.from(values.buffer, values.byteOffset, values.byteLength).toString('base64');
  }} catch (error) {{
    if (error instanceof BundleError) return null;
    return `crashed: ${{error}}`;
  }}
}})));
""")
    done = subprocess.run([node, str(script)], capture_output=True, text=True, timeout=NODE_TIMEOUT_S)
    assert done.returncode == 0, done.stderr[-2000:]
    web = json.loads(done.stdout)
    wrong = [index for index, (case, got) in enumerate(zip(cases, web, strict=True)) if case["want"] != got]
    assert not wrong, [(index, web[index] if web[index] is None else str(web[index])[:40]) for index in wrong[:10]]
    assert cases[0]["want"] is not None and sum(case["want"] is None for case in cases) > 50


def _vq_payload(halves: np.ndarray, index: np.ndarray, bits: int) -> bytes:
    """A `vq` payload made by hand (docs/bundle-format.md, "vq"): the codebook's half bits, then each index's `bits`
    bits, the lowest first, in one stream."""
    stream = ((np.asarray(index, np.int64)[:, None] >> np.arange(bits)) & 1).astype(np.uint8).reshape(-1)
    return np.asarray(halves, "<u2").tobytes() + np.packbits(stream, bitorder="little").tobytes()


def _with_byte(payload: bytes, at: int, value: int) -> bytes:
    return payload[:at] + bytes([value]) + payload[at + 1:]


def _vq_cases() -> list[dict]:
    """Decode cases: (payload, dtype, shape, params) of vq buffers encoded by sdk/codecs.py or made by hand, intact
    and damaged (a codebook value not finite, an index past K, a bit past the last index, a bad `entries`)."""
    from gaussiantalker.sdk.codecs import encode_buffer

    rng = np.random.default_rng(4)
    mostly_zero = rng.standard_normal((4, 50)).astype(np.float32)
    mostly_zero[rng.random((4, 50)) < 0.8] = 0
    arrays = [(rng.standard_normal((3, 20)), 1, False), (rng.standard_normal((2, 33)), 2, False),
              (rng.standard_normal((2, 50)), 3, False), (rng.standard_normal((4, 30)), 12, False),
              (rng.standard_normal((3, 400)), 300, False), (rng.standard_normal(37), 5, False),
              (rng.standard_normal((2, 3, 25)), 7, False), (np.float32(1.5), None, False),
              (np.zeros((3, 0)), 5, False), (np.zeros((0, 4)), 5, False),
              (rng.standard_normal((2, 40)).astype(np.float16), 12, False), (mostly_zero, 5, True),
              (mostly_zero.astype(np.float16), 3, True)]
    cases = []
    for array, entries, sparse in arrays:
        array = np.asarray(array, array.dtype if array.dtype == np.float16 else np.float32)
        payload, params = encode_buffer(array, "vq", entries, sparse)
        cases.append((payload, str(array.dtype), array.shape, params))
    special = np.array([0x8000, 0x0001, 0x7BFF, 0xFBFF, 0x3555, 0x03FF], np.uint16)  # -0, subnormals, +-65504
    index = rng.integers(0, 6, 29)
    cases.append((_vq_payload(special, index, 3), "float32", (29,), {"entries": 6}))
    cases.append((_vq_payload(special, index, 3), "float16", (29,), {"entries": 6}))
    wide = rng.integers(0, 0x7C00, 65536).astype(np.uint16)  # K = 65536: 16-bit indices
    cases.append((_vq_payload(wide, rng.integers(0, 65536, 11), 16), "float32", (11,), {"entries": 65536}))
    for entries, bits in ((257, 9), (1000, 10), (20000, 15)):  # indices over three bytes of the stream
        cases.append((_vq_payload(np.resize(special, entries), rng.integers(0, entries, 23), bits), "float32", (23,),
                      {"entries": entries}))
    damaged = []
    for payload, dtype, shape, params in cases[:13]:
        if "sparse" in params:
            continue
        entries, width = params["entries"], int(np.prod(shape[:-1], dtype=np.int64)) if shape else 1
        table = 2 * entries * width
        if table:  # an infinity, a NaN
            damaged.append((payload[:table - 2] + b"\x00\x7c" + payload[table:], dtype, shape, params))
            damaged.append((b"\x01\xfe" + payload[2:], dtype, shape, params))
        used = (shape[-1] if shape else 1) * max(1, (entries - 1).bit_length())
        if used % 8:  # a stray bit past the last index
            damaged.append((_with_byte(payload, len(payload) - 1, payload[-1] | 0x80), dtype, shape, params))
        for bad in (0, 65537, "3", 2.5, True, None):
            damaged.append((payload, dtype, shape, {**params, "entries": bad}))
    for entries, vectors in ((3, 50), (12, 30), (300, 400), (5, 37)):  # an index at or past K (b-bit stream)
        bits = max(1, (entries - 1).bit_length())
        for past in (entries, 2 ** bits - 1):
            if past < 2 ** bits:
                index = np.arange(vectors) % entries
                index[vectors // 2] = past
                damaged.append((_vq_payload(np.full(entries, 0x3C00), index, bits), "float32", (vectors,),
                                {"entries": entries}))
    return [{"payload": payload, "dtype": dtype, "shape": list(shape), "params": params}
            for payload, dtype, shape, params in cases + damaged]


def _vq_sizes() -> list[dict]:
    """expectedNbytes cases: vq's size on every kind of shape, huge ones included, and what it refuses."""
    shapes = [[4, 13012], [], [0], [5, 0], [0, 5], [7], [2, 3, 25], [2 ** 20, 2 ** 20], [3, 2 ** 40]]
    cases = [("float32", shape, {"entries": entries}) for shape in shapes for entries in (1, 2, 3, 256, 257, 65536)]
    cases += [("float16", [2, 40], {"entries": 12}), ("int32", [2, 40], {"entries": 12}),
              ("int64", [5], {"entries": 2}), ("float32", [3, 10], {"entries": 5, "sparse": {"nnz": 7}}),
              ("float32", [3, 10], {"entries": 5, "sparse": {"nnz": 7, "mask_zlib": 12}})]
    cases += [("float32", [4, 30], {"entries": bad}) for bad in (0, -1, 65537, 2 ** 40, "12", 2.5, True, None)]
    cases.append(("float32", [4, 30], {}))
    return [{"dtype": dtype, "shape": shape, "params": params} for dtype, shape, params in cases]


def _zlib_bundles(folder: Path) -> list[Path]:
    """Bundles whose buffers are stored zlib-compressed (vq, q8, raw, index, sparse, a large raw one), intact, then
    with one buffer's entry or stream damaged (checksums and offsets made to match, so only the damage remains)."""
    import zlib

    from test_fuzz_readers import _relayout

    from gaussiantalker.sdk.bundle import Bundle, BundleWriter
    from gaussiantalker.sdk.codecs import zlib_bound

    rng = np.random.default_rng(6)
    values = np.tile(rng.standard_normal((3, 8)).astype(np.float32), 30)
    big = rng.standard_normal(20000).astype(np.float32)
    sparse = values.copy()
    sparse[:, rng.random(240) < 0.7] = 0
    writer = BundleWriter()
    for name, array, codec, chunk, is_sparse in (("vq", values, "vq", 12, False), ("q8", values, "q8", 16, False),
                                                 ("raw", values, "raw", None, False),
                                                 ("ids", np.arange(300) % 7, "index", None, False),
                                                 ("sparse", sparse, "q8", 16, True),
                                                 ("big", big, "raw", None, False)):
        writer.add_buffer(name, array, codec, chunk, is_sparse, compress=True)
    writer.add_buffer("plain", values[:, :8], "vq", 3)
    writer.write(folder / "zlib.gtb")
    bundle = Bundle(folder / "zlib.gtb")
    manifest = json.loads(json.dumps(bundle.manifest))
    assert all(manifest["buffers"][name].get("compression") == "zlib" for name in ("vq", "q8", "raw", "ids", "sparse"))
    assert manifest["buffers"]["big"]["nbytes"] > 3 * 16384  # a stream fflate is given in several pushes
    blobs = {("buffers", name): bundle._read_entry(name, entry) for name, entry in manifest["buffers"].items()}
    paths = [folder / "zlib.gtb"]

    def variant(name: str, stream: bytes | None = None, **entry) -> None:
        changed = json.loads(json.dumps(manifest))
        changed["buffers"][name].update(entry)
        path = folder / f"zlib{len(paths):03d}.gtb"
        path.write_bytes(_relayout(changed, {**blobs, ("buffers", name): blobs["buffers", name] if stream is None
                                             else stream}))
        paths.append(path)

    for name in ("vq", "q8", "sparse", "big"):
        raw = manifest["buffers"][name]["raw_nbytes"]
        payload = zlib.decompress(blobs["buffers", name])
        stream = blobs["buffers", name]
        for wrong in (raw - 1, raw + 1, -1, 2 ** 31, "12", None):
            variant(name, raw_nbytes=wrong)
        for unknown in ("gzip", "", 7, None):
            variant(name, compression=unknown)
        variant(name, zlib.compress(payload, 0))  # stored blocks: loads
        variant(name, zlib.compress(payload[:-1]))  # one byte short, or one too many
        variant(name, zlib.compress(payload + b"\0"))
        variant(name, zlib.compress(payload + b"\0"), raw_nbytes=raw + 1)  # a raw_nbytes the codec does not imply
        variant(name, zlib.compress(payload[:-1]), raw_nbytes=raw - 1)
        variant(name, zlib.compress(bytes(100 * raw)))  # far more, in few bytes
        compressor = zlib.compressobj(9)
        head = compressor.compress(payload) + compressor.flush(zlib.Z_SYNC_FLUSH)  # byte-aligned here
        tail = compressor.flush()
        for blocks in (2, (zlib_bound(raw) - len(head + tail)) // 5 + 1):  # empty stored blocks: a valid stream,
            variant(name, head + b"\0\0\0\xff\xff" * blocks + tail)  # then one longer than zlib's bound
        variant(name, payload)  # not a zlib stream
        variant(name, stream[:-1])  # cut short, or cut in its DEFLATE data
        variant(name, stream[:len(stream) // 2] + stream[-4:])
        variant(name, stream[:-4] + bytes(4))  # a wrong checksum, bytes after it
        variant(name, stream + bytes(2))
        for _ in range(8):
            damaged = bytearray(stream)
            damaged[rng.integers(len(damaged))] ^= 1 << int(rng.integers(8))
            variant(name, bytes(damaged))
    vq = zlib.decompress(blobs["buffers", "vq"])
    variant("vq", zlib.compress(_with_byte(vq, 2 * 12 * 3, 0xFF)))  # inflates, then an index is past K
    return paths


def test_the_web_reader_decodes_and_refuses_vq_and_deflated_buffers_as_python_does(tmp_path):
    """`decodeBuffer` and `expectedNbytes` (web/src/codecs.js) against sdk/codecs.py on `vq` buffers (K = 1, 2, 3,
    12, 257, 300, 65536; 0-d, 1-D, 3-D and empty shapes; float32 and float16; sparse; a codebook with -0, subnormals
    and +-65504), intact and damaged; and `readBundle` + `buffer` (web/src/bundle.js) against sdk/bundle.py on
    buffers stored zlib-compressed, intact and with their raw_nbytes, compression or stream damaged: the same bytes
    where Python decodes, refused where Python refuses."""
    import base64

    from gaussiantalker.sdk.bundle import Bundle
    from gaussiantalker.sdk.codecs import decode_buffer, expected_nbytes

    node = shutil.which("node")
    need(None if node else "node is missing (Debian's npm brings it)", BROWSER_INSTALL)
    decodes, sizes, bundles = _vq_cases(), _vq_sizes(), _zlib_bundles(tmp_path)

    def python(read):
        try:
            return read()
        except BundleError:
            return None

    for case in decodes:
        case["want"] = python(lambda c=case: base64.b64encode(decode_buffer(
            c["payload"], "vq", c["dtype"], tuple(c["shape"]), c["params"]).tobytes()).decode())
        case["payload"] = base64.b64encode(case["payload"]).decode()
    for case in sizes:
        case["want"] = python(lambda c=case: str(expected_nbytes("vq", c["dtype"], tuple(c["shape"]), c["params"])))

    def read_bundle(path: Path) -> list[str]:
        bundle = Bundle(path)
        bundle.verify_all()
        return [base64.b64encode(bundle.buffer(name).tobytes()).decode() for name in sorted(bundle.manifest["buffers"])]

    want_bundles = [python(lambda p=path: read_bundle(p)) for path in bundles]
    (tmp_path / "cases.json").write_text(json.dumps({"decodes": decodes, "sizes": sizes,
                                                     "bundles": [str(path) for path in bundles]}))
    script = tmp_path / "vq.mjs"
    script.write_text(f"""
import fs from 'node:fs';
import {{ readBundle }} from {json.dumps((ROOT / "web" / "src" / "bundle.js").as_uri())};
import {{ BundleError, decodeBuffer, expectedNbytes }} from {json.dumps((ROOT / "web" / "src" / "codecs.js").as_uri())};
const {{ decodes, sizes, bundles }} = JSON.parse(fs.readFileSync({json.dumps(str(tmp_path / "cases.json"))}, 'utf8'));
const base64 = (values) => Buffer.from(values.buffer, values.byteOffset, values.byteLength).toString('base64');
async function verdict(read) {{
  try {{
    return await read();
  }} catch (error) {{
    if (error instanceof BundleError && !error.message.includes('\\n')) return null;
    return `crashed: ${{error}}`;
  }}
}}
const results = {{ decodes: [], sizes: [], bundles: [] }};
for (const {{ payload, dtype, shape, params }} of decodes) {{
  results.decodes.push(await verdict(() => base64(decodeBuffer(new Uint8Array(Buffer.from(payload, 'base64')), 'vq',
    dtype, shape, params))));
}}
for (const {{ dtype, shape, params }} of sizes) {{
  results.sizes.push(await verdict(() => String(expectedNbytes('vq', dtype, shape, params))));
}}
for (const path of bundles) {{
  results.bundles.push(await verdict(async () => {{
    const bundle = await readBundle(fs.readFileSync(path), {{ name: path }});
    return Object.keys(bundle.manifest.buffers).sort().map((name) => base64(bundle.buffer(name).data));
  }}));
}}
console.log(JSON.stringify(results));
""")
    done = subprocess.run([node, str(script)], capture_output=True, text=True, timeout=NODE_TIMEOUT_S)
    assert done.returncode == 0, done.stderr[-2000:]
    web = json.loads(done.stdout)
    wrong = [f"{kind} {index}: Python {str(want)[:60]}, web {str(got)[:60]}"
             for kind, wants in (("decode", [c["want"] for c in decodes]), ("size", [c["want"] for c in sizes]),
                                 ("bundle", want_bundles))
             for index, (want, got) in enumerate(zip(wants, web[kind + "s"], strict=True)) if want != got]
    assert not wrong, "\n".join(wrong[:20]) + f"\n({len(wrong)} in all)"
    for wants in ([c["want"] for c in decodes], [c["want"] for c in sizes], want_bundles):  # both ends reached
        assert sum(want is None for want in wants) > 5 and sum(want is not None for want in wants) >= 4
    assert want_bundles[0] is not None  # the intact bundle


def _graph_bundles(folder: Path) -> list[Path]:
    """Bundles holding one zlib-stored graph: intact, then its stream or entry damaged (checksums and offsets made to
    match): bytes after the stream (also a copy of its checksum after them), cut short, a wrong checksum, another
    raw_nbytes, not zlib, a flipped bit."""
    import zlib

    from test_fuzz_readers import _relayout

    from gaussiantalker.sdk.bundle import Bundle, BundleWriter

    rng = np.random.default_rng(11)
    graph = bytes(rng.integers(0, 8, 6000, dtype=np.uint8))  # compressible, as a protobuf is
    writer = BundleWriter({"speaker": {"n_expr": 3}})
    writer.add_buffer("weights", np.zeros(3, np.float32))
    writer.add_graph("g", graph, [], [], {"w": "weights"})
    writer.write(folder / "graph.gtb")
    bundle = Bundle(folder / "graph.gtb")
    manifest = json.loads(json.dumps(bundle.manifest))
    assert manifest["graphs"]["g"].get("compression") == "zlib"
    blobs = {("buffers", "weights"): bundle._read_entry("weights", manifest["buffers"]["weights"]),
             ("graphs", "g"): bundle._read_entry("g", manifest["graphs"]["g"])}
    stream, raw = blobs["graphs", "g"], len(graph)
    paths = [folder / "graph.gtb"]

    def variant(data: bytes, **entry) -> None:
        changed = json.loads(json.dumps(manifest))
        changed["graphs"]["g"].update(entry)
        path = folder / f"graph{len(paths):03d}.gtb"
        path.write_bytes(_relayout(changed, {**blobs, ("graphs", "g"): data}))
        paths.append(path)

    for extra in (b"\0", bytes(7), b"\x01\x02\x03" + stream[-4:], stream):  # after the stream, however it ends
        variant(stream + extra)
    variant(stream[:-1])
    variant(stream[:-4] + bytes(4))
    variant(stream, raw_nbytes=raw - 1)
    variant(stream, raw_nbytes=raw + 1)
    variant(graph, raw_nbytes=raw)  # not a zlib stream
    variant(zlib.compress(graph, 0))  # stored blocks: loads
    for _ in range(4):
        damaged = bytearray(stream)
        damaged[rng.integers(len(damaged))] ^= 1 << int(rng.integers(8))
        variant(bytes(damaged))
    return paths


def test_the_web_reader_inflates_and_refuses_graphs_as_python_does(tmp_path):
    """`graphBytes` (web/src/bundle.js) against sdk/bundle.py `graph_bytes` on a zlib-stored graph, intact and
    damaged: the same bytes where Python inflates them, refused where Python refuses (bytes after the stream's
    checksum too, which the platform's inflater alone lets through)."""
    import base64

    from gaussiantalker.sdk.bundle import Bundle

    node = shutil.which("node")
    need(None if node else "node is missing (Debian's npm brings it)", BROWSER_INSTALL)
    paths = _graph_bundles(tmp_path)

    def python(path: Path) -> str | None:
        try:
            return base64.b64encode(Bundle(path).graph_bytes("g")).decode()
        except BundleError:
            return None

    want = [python(path) for path in paths]
    script = tmp_path / "graphs.mjs"
    script.write_text(f"""
import fs from 'node:fs';
import {{ readBundle, BundleError }} from {json.dumps((ROOT / "web" / "src" / "bundle.js").as_uri())};
const results = [];
for (const path of {json.dumps([str(path) for path in paths])}) {{
  try {{
    const bundle = await readBundle(fs.readFileSync(path), {{ name: path }});
    results.push(Buffer.from(await bundle.graphBytes('g')).toString('base64'));
  }} catch (error) {{
    results.push(error instanceof BundleError && !error.message.includes('\\n') ? null : `crashed: ${{error}}`);
  }}
}}
console.log(JSON.stringify(results));
""")
    done = subprocess.run([node, str(script)], capture_output=True, text=True, timeout=NODE_TIMEOUT_S)
    assert done.returncode == 0, done.stderr[-2000:]
    web = json.loads(done.stdout)
    wrong = [f"{path.name}: Python {str(a)[:40]}, web {str(b)[:40]}"
             for path, a, b in zip(paths, want, web, strict=True) if a != b]
    assert not wrong, "\n".join(wrong)
    assert want[0] is not None and want[-5] is not None and sum(w is None for w in want) >= 10


def test_the_web_npy_reader_reads_dtypes_as_numpy_does(tmp_path):
    """`parseDescr` (web/src/npy_header.js) against numpy on every one-character type code and every kind letter
    with sizes 0-20, 32, 64, 99, each with each byte-order mark: the same numbers dtype (kind, size, byte order), a
    string, or refused. float128 is the one numpy reads and the browser refuses (docs/untrusted-input.md)."""
    import warnings

    node = shutil.which("node")
    need(None if node else "node is missing (Debian's npm brings it)", BROWSER_INSTALL)
    cases = []
    bodies = [chr(c) for c in range(256)] + [k + str(n) for k in "biufSaUcVOMm?" for n in [*range(21), 32, 64, 99]]
    for descr in (order + body for order in ("", "<", ">", "|", "=") for body in bodies):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                dtype = np.dtype(descr)
        except (TypeError, ValueError, SyntaxError):
            cases.append([descr, None])
            continue
        if dtype.hasobject or dtype.names is not None or dtype.subdtype is not None or dtype.kind not in "biufUS" \
                or dtype.itemsize == 0 or (dtype.kind == "f" and dtype.itemsize > 8):
            cases.append([descr, None])
        else:
            cases.append([descr, [dtype.kind, dtype.itemsize, dtype.kind not in "US" and dtype.byteorder == ">"]])
    (tmp_path / "cases.json").write_text(json.dumps(cases))
    script = tmp_path / "descr.mjs"
    script.write_text(f"""
import fs from 'node:fs';
import {{ parseDescr }} from {json.dumps((ROOT / "web" / "src" / "npy_header.js").as_uri())};
const cases = JSON.parse(fs.readFileSync({json.dumps(str(tmp_path / "cases.json"))}, 'utf8'));
console.log(JSON.stringify(cases.map(([descr]) => {{
  const d = parseDescr(descr);
  return d === null ? null : [d.kind, d.size, d.kind !== 'S' && d.kind !== 'U' && d.bigEndian];
}})));
""")
    done = subprocess.run([node, str(script)], capture_output=True, text=True, timeout=NODE_TIMEOUT_S)
    assert done.returncode == 0, done.stderr[-2000:]
    web = json.loads(done.stdout)
    pairs = zip(cases, web, strict=True)
    wrong = [f"{descr!r}: numpy {want}, web {got}" for (descr, want), got in pairs if want != got]
    assert not wrong, "\n".join(wrong[:20])
    assert sum(want is not None for _, want in cases) > 100  # the table holds many readable dtypes


@pytest.mark.parametrize("run, seed", [pytest.param("ci", 0, id="ci"),
                                       pytest.param("heavy", 1000, id="heavy", marks=pytest.mark.heavy)])
def test_fuzz_the_web_drive_decoder(tmp_path, run, seed):
    """Live drive messages (gaussiantalker.serve.wire `encode_drive`, FLAME and ARKit) with header fields set to
    0/-1/huge, bytes mutated anywhere and values made non-finite, through `decodeDrive` against `decode_drive`."""
    from test_live_web import _server_module

    server = _server_module()
    flame = SimpleNamespace(expression=np.linspace(-1, 1, 10, dtype=np.float32),
                            flame_pose=np.full(15, 0.1, np.float32), head_translation=np.zeros(3, np.float32))
    arkit = SimpleNamespace(blendshapes=np.linspace(0, 1, 52, dtype=np.float32),
                            head_rotation=np.zeros(3, np.float32), head_translation=np.ones(3, np.float32))
    messages = [server.encode_drive(7, 0.28, flame, True, 2), server.encode_drive(0, 0.0, arkit, False, 0)]
    fields = [(4, 1), (5, 1), (6, 1), (7, 1), (8, 4), (12, 4), (16, 8), (24, 2), (26, 2)]
    rng = np.random.default_rng(seed + 11)
    cases = []
    for index in range(CASES[run]):
        message, choice = messages[index % 2], rng.random()
        if choice < 0.4:
            data, what = mutate_field_bytes(message, rng, fields)
        elif choice < 0.55:
            values = bytearray(message)
            at = server.DRIVE_HEADER.size + 4 * int(rng.integers((len(message) - server.DRIVE_HEADER.size) // 4))
            values[at:at + 4] = struct.pack("<f", float(rng.choice([np.nan, np.inf, -np.inf, 3e38, -0.0])))
            data, what = bytes(values), f"value at byte {at} replaced"
        else:
            data, what = mutate_bytes(message, rng, protect=4 if choice < 0.85 else 0)
        path = tmp_path / f"drive{index:05d}.bin"
        path.write_bytes(data)
        cases.append((path, what))

    web = _check_verdicts("drive", cases, lambda path: server.decode_drive(path.read_bytes()), server.DriveFormatError,
                          tmp_path, names_file=False)
    assert 0 < sum(r["verdict"] == "loaded" for r in web) < len(cases)
