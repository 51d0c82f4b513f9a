"""Every reader of a user's file, fuzzed (docs/untrusted-input.md): valid files the test helpers write are mutated
at byte level and value level (tests/fuzz_mutations.py, a seeded numpy Generator), and each case must either load or
raise the SDK's own error, in one line naming the file, within MAX_CASE_SECONDS and MAX_CASE_BYTES of traced memory.
Any other exception, a hang or a large allocation fails the test, which lists the cases (seed and index reproduce
each). The CI run takes a few hundred cases per reader; `GT_HEAVY=1 python -m pytest -q -m heavy
tests/test_fuzz_readers.py` takes ten times as many with other seeds.

Bounds: no case may raise anything but GaussianTalkerError (the reader's documented subclass where it has one), take
over MAX_CASE_SECONDS, or allocate over MAX_CASE_BYTES (numpy and Python allocations, tracemalloc); a fuzz that
refuses nothing, or loads nothing where loading is possible, fails too (its mutations would not be biting).
"""

from __future__ import annotations

import io
import json
import os
import re
import signal
import struct
import time
import traceback
import tracemalloc
import zipfile
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from fuzz_mutations import (
    dumps,
    glb_fields,
    glb_join,
    glb_split,
    mutate_bytes,
    mutate_field_bytes,
    mutate_json,
    mutate_npz_arrays,
    mutate_zip_field,
    npz_bytes,
    unsafe_name,
    write_zip,
)

from gaussiantalker.sdk.errors import (
    BundleError,
    CheckpointError,
    DriveError,
    GaussianTalkerError,
    ImportFormatError,
)

# A case taking longer has hung (the slowest valid case here takes well under a second); a case tracing more
# memory has allocated from a header field (the valid files are kilobytes, their readers need a few MB).
MAX_CASE_SECONDS = 10.0
MAX_CASE_BYTES = 256 << 20
HEAVY = 10  # the heavy variant's cases per CI case


class _Hung(BaseException):
    """Raised in a case that runs past MAX_CASE_SECONDS (a BaseException, so no reader's handler swallows it)."""


@dataclass
class Case:
    """One fuzz case: what was done to the valid file, and the reader's argument (a path, or bytes)."""

    what: str
    argument: object
    label: str  # what the error message must name (the file's path or the member)


def _mutated_npz(params: dict, rng: np.random.Generator, arrays_below: float, zip_below: float) -> tuple[bytes, str]:
    """An npz of `params` mutated at one level, chosen by one draw: its arrays (below `arrays_below`), a zip header
    field (below `zip_below`), or its bytes."""
    choice = rng.random()
    if choice < arrays_below:
        return mutate_npz_arrays(params, rng)
    if choice < zip_below:
        return mutate_zip_field(npz_bytes(params), rng)
    return mutate_bytes(npz_bytes(params), rng)


def fuzz(reader: Callable[[object], object], make_case: Callable[[np.random.Generator, int], Case], count: int,
         seed: int, error: type[Exception] = GaussianTalkerError, must_load: bool = True) -> Counter:
    """Run `count` cases; every case loads or raises `error` in one line naming its label. Returns the counts."""
    rng = np.random.default_rng(seed)
    outcome: Counter = Counter()
    failures: list[str] = []

    def hung(signum, frame):
        raise _Hung()

    previous = signal.signal(signal.SIGALRM, hung)
    tracemalloc.start()
    try:
        for index in range(count):
            case = make_case(rng, index)
            where = f"seed {seed} case {index} ({case.what})"
            tracemalloc.reset_peak()
            start = time.perf_counter()
            signal.setitimer(signal.ITIMER_REAL, 2 * MAX_CASE_SECONDS)
            try:
                reader(case.argument)
                outcome["loaded"] += 1
            except error as exc:
                outcome["refused"] += 1
                text = str(exc)
                if "\n" in text or case.label not in text:
                    failures.append(f"{where}: the message is not one line naming {case.label}: {text[:300]!r}")
            except _Hung:
                failures.append(f"{where}: still running after {2 * MAX_CASE_SECONDS} s")
            except Exception as exc:  # the defect this test looks for: any other error escaping the reader
                frame = traceback.extract_tb(exc.__traceback__)[-1]
                failures.append(f"{where}: {type(exc).__name__} at {Path(frame.filename).name}:{frame.lineno}: "
                                f"{' '.join(str(exc).split())[:200]}")
            finally:
                signal.setitimer(signal.ITIMER_REAL, 0)
            seconds, peak = time.perf_counter() - start, tracemalloc.get_traced_memory()[1]
            if seconds > MAX_CASE_SECONDS:
                failures.append(f"{where}: took {seconds:.1f} s")
            if peak > MAX_CASE_BYTES:
                failures.append(f"{where}: allocated {peak / 2**20:.0f} MiB")
    finally:
        tracemalloc.stop()
        signal.signal(signal.SIGALRM, previous)
    print(f"seed {seed}: {count} cases, {dict(outcome)}")  # shown with -s
    assert not failures, f"{len(failures)} of {count} cases failed:\n" + "\n".join(failures[:40])
    assert outcome["refused"] > 0, f"no case was refused: the mutations do not bite ({dict(outcome)})"
    if must_load:
        assert outcome["loaded"] > 0, f"no case loaded: the valid file or the harness is broken ({dict(outcome)})"
    return outcome


def _counts(ci: int, heavy: bool) -> int:
    return ci * HEAVY if heavy else ci


RUNS = [pytest.param(False, 0, id="ci"), pytest.param(True, 1000, id="heavy", marks=pytest.mark.heavy)]


# -- LAM avatar zips: the members (glb, PLY, JSON) --------------------------------------------------------------


@pytest.fixture(scope="module")
def lam_members(tmp_path_factory) -> dict[str, bytes]:
    from lam_avatars import AvatarSpec, write_avatar_zip

    # subdivided: its skin.glb carries the mesh's triangles (an `indices` accessor) for the mutations to reach too
    path = write_avatar_zip(tmp_path_factory.mktemp("fuzz_lam") / "avatar.zip", AvatarSpec(subdivided=True))
    with zipfile.ZipFile(path) as archive:
        return {info.filename: archive.read(info) for info in archive.infolist()}


def _ply_header_mutation(data: bytes, rng: np.random.Generator) -> tuple[bytes, str]:
    """A PLY with one header line changed: a count, a type, a name, the format, a line dropped or repeated."""
    end = data.index(b"end_header\n") + len(b"end_header\n")
    lines, body = data[:end].decode("latin-1").splitlines(), data[end:]
    index = int(rng.integers(1, len(lines) - 1))
    words = lines[index].split()
    kind = int(rng.integers(7))
    if kind == 0 and words[0] == "element":
        words[2] = str([0, 1, -1, 10**12, 2**63, int(words[2]) + 1, int(words[2]) * 2, "x"][int(rng.integers(8))])
    elif kind == 1 and words[0] == "property":
        words[1:2] = [["double", "uchar", "int", "char", "list uchar float", "list uint double", "half", ""][
            int(rng.integers(8))]]
    elif kind == 2 and words[0] == "property":
        words[-1] = ["f_rest_x", "f_rest_999999", "x", "binding_0", "f_rest_", "", "nx"][int(rng.integers(7))]
    elif kind == 3:
        lines[1] = ["format ascii 1.0", "format binary_big_endian 1.0", "format binary_little_endian 2.0",
                    "format", "formats binary_little_endian 1.0"][int(rng.integers(5))]
    elif kind == 4:
        del lines[index]
    elif kind == 5:
        lines.insert(index, lines[index])
    else:
        lines.insert(index, ["comment " + "x" * 2000, "obj_info a", "element extra 3", "property float z",
                             "element vertex 5"][int(rng.integers(5))])
    if kind <= 2:
        lines[index] = " ".join(str(w) for w in words)
    newline = "\r\n" if rng.random() < 0.1 else "\n"
    what = f"PLY header line {index}: {lines[min(index, len(lines) - 1)][:40]}"
    return (newline.join(lines) + newline).encode("latin-1") + body, what


def _mutate_member(name: str, data: bytes, rng: np.random.Generator) -> tuple[bytes, str]:
    """A byte-level or value-level mutation suited to the member's format."""
    kind = rng.random()
    if name.endswith(".glb"):
        if kind < 0.4:
            doc, rest = glb_split(data)
            document, what = mutate_json(doc, rng)
            return glb_join(dumps(document), rest), f"glTF JSON: {what}"
        if kind < 0.55:
            return mutate_field_bytes(data, rng, glb_fields(data))
        return mutate_bytes(data, rng)
    if name.endswith(".json"):
        if kind < 0.7:
            document, what = mutate_json(json.loads(data), rng)
            return dumps(document), what
        return mutate_bytes(data, rng)
    if kind < 0.5:
        return _ply_header_mutation(data, rng)
    return mutate_bytes(data, rng)


def _lam_member_case(members: dict[str, bytes], folder: Path) -> Callable[[np.random.Generator, int], Case]:
    names = [name for name in members if name.rsplit("/", 1)[-1] in ("skin.glb", "offset.ply", "animation.glb",
                                                                      "bsData.json", "vertex_order.json")]

    def make(rng: np.random.Generator, index: int) -> Case:
        name = names[int(rng.integers(len(names)))]
        changed, what = _mutate_member(name, members[name], rng)
        path = folder / f"case{index % 4}.zip"
        path.write_bytes(write_zip([(n, changed if n == name else d) for n, d in members.items()]))
        return Case(f"{name}: {what}", path, str(path))
    return make


@pytest.mark.parametrize("heavy, seed", RUNS)
def test_fuzz_lam_avatar_members(lam_members, tmp_path, heavy, seed):
    """skin.glb, animation.glb (glTF container fields, JSON values), offset.ply (header lines, bytes), bsData.json
    and vertex_order.json (JSON values) mutated inside an otherwise valid avatar zip: import_lam loads or refuses
    with ImportFormatError naming the zip."""
    from gaussiantalker.exporter.imports.sources.lam import import_lam

    fuzz(lambda path: import_lam(path, progress=False), _lam_member_case(lam_members, tmp_path),
         _counts(300, heavy), seed, ImportFormatError)


# -- LAM avatar zips: the archive --------------------------------------------------------------------------------


def _bomb(rng: np.random.Generator) -> tuple[str, bytes, int]:
    """(what, member bytes, method) of a member that inflates far beyond its compressed size."""
    name, method = [("deflate", zipfile.ZIP_DEFLATED), ("bzip2", zipfile.ZIP_BZIP2), ("lzma", zipfile.ZIP_LZMA)][
        int(rng.integers(3))]
    size = int(rng.integers(1, 40)) << 20
    return f"a {name} bomb of {size >> 20} MiB", bytes(size), method


def _lam_zip_case(members: dict[str, bytes], folder: Path) -> Callable[[np.random.Generator, int], Case]:
    items = list(members.items())

    def make(rng: np.random.Generator, index: int) -> Case:
        path = folder / f"case{index % 4}.zip"
        kind = int(rng.integers(7))
        target = int(rng.integers(1, len(items)))
        name, data = items[target]
        if kind == 0:
            changed, what = mutate_bytes(write_zip(items), rng)
        elif kind == 1:
            changed, what = mutate_zip_field(write_zip(items, [zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED][
                int(rng.integers(2))]), rng)
        elif kind == 2:
            new = unsafe_name(rng, name.split("/")[0], name.rsplit("/", 1)[-1])
            changed, what = write_zip([(new if i == target else n, d) for i, (n, d) in enumerate(items)]), \
                f"{name} renamed {new!r}"
        elif kind == 3:
            changed, what = write_zip(items + [(name, data[::-1])]), f"{name} twice"
        elif kind == 4:
            what, bomb, method = _bomb(rng)
            buffer = io.BytesIO()
            with zipfile.ZipFile(buffer, "w") as archive:
                for n, d in items:
                    if n == name:
                        archive.writestr(n, bomb, compress_type=method)
                    else:
                        archive.writestr(n, d)
            changed, what = buffer.getvalue(), f"{name} is {what}"
        elif kind == 5:
            methods = [(n, d, zipfile.ZIP_DEFLATED if rng.integers(2) else zipfile.ZIP_BZIP2) for n, d in items]
            buffer = io.BytesIO()
            with zipfile.ZipFile(buffer, "w") as archive:
                for n, d, m in methods:
                    archive.writestr(n, d, compress_type=m)
            changed, what = mutate_bytes(buffer.getvalue(), rng)
            what = f"compressed members: {what}"
        else:
            changed, what = write_zip([(n, d) for i, (n, d) in enumerate(items) if i != target]), f"no {name}"
        path.write_bytes(changed)
        return Case(what, path, str(path))
    return make


@pytest.mark.parametrize("heavy, seed", RUNS)
def test_fuzz_lam_avatar_zip(lam_members, tmp_path, heavy, seed):
    """The zip itself: bytes mutated, header fields (sizes, methods, flags, offsets) set to 0/-1/huge in the local
    header or the central directory, members renamed out of their folder, duplicated, made into bombs, removed."""
    from gaussiantalker.exporter.imports.sources.lam import import_lam

    fuzz(lambda path: import_lam(path, progress=False), _lam_zip_case(lam_members, tmp_path), _counts(150, heavy),
         seed + 1, ImportFormatError)


# -- PLY ----------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def ply_files() -> list[bytes]:
    """A LAM offset.ply and a GaussianAvatars point_cloud.ply (SH degree 3, binding_0), binary little-endian."""
    from gaussian_avatars import _gaussians, ply_field_names
    from lam_avatars import AvatarSpec, offset_ply
    from plyfile import PlyData, PlyElement

    fields = _gaussians(30, 3, np.random.default_rng(0))
    records = np.empty(30, dtype=[(name, "<f4") for name in ply_field_names(3)])
    for name, values in fields.items():
        records[name] = values
    buffer = io.BytesIO()
    PlyData([PlyElement.describe(records, "vertex")], text=False, byte_order="<").write(buffer)
    return [offset_ply(AvatarSpec()), buffer.getvalue()]


@pytest.mark.parametrize("heavy, seed", RUNS)
def test_fuzz_gaussian_ply(ply_files, heavy, seed):
    """read_gaussian_ply on header-line and byte mutations of two real layouts (and ASCII or big-endian rewrites)."""
    from gaussiantalker.exporter.imports.formats.gaussian_ply import read_gaussian_ply

    def make(rng: np.random.Generator, index: int) -> Case:
        data = ply_files[index % 2]
        changed, what = _ply_header_mutation(data, rng) if rng.random() < 0.5 else mutate_bytes(data, rng)
        if rng.random() < 0.3:
            changed, more = _ply_header_mutation(changed, rng) if changed.count(b"end_header\n") == 1 else \
                mutate_bytes(changed, rng)
            what += f"; {more}"
        return Case(what, changed, "member.ply")

    fuzz(lambda data: read_gaussian_ply(data, "member.ply"), make, _counts(400, heavy), seed + 2, ImportFormatError)


# -- GaussianAvatars folders --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def ga_avatar(tmp_path_factory):
    """A small GaussianAvatars avatar on the synthetic FLAME-layout model, and that model with the teeth added."""
    from gaussian_avatars import synthetic_flame, write_flame_npz, write_gaussian_avatar

    from gaussiantalker.exporter.imports.sources.gaussian_avatars_flame import load_gaussian_avatars_flame

    root = tmp_path_factory.mktemp("fuzz_ga")
    model = synthetic_flame(0)
    written = write_gaussian_avatar(root / "avatar", model, n_gaussians=40, frames=4)
    flame = write_flame_npz(root / "flame.npz", model)
    with np.load(written["param_path"]) as data:
        params = {key: data[key] for key in data.files}
    return {"root": root, "written": written, "params": params, "flame_path": flame,
            "arrays": load_gaussian_avatars_flame(flame)}


@pytest.mark.parametrize("heavy, seed", RUNS)
def test_fuzz_gaussian_avatars_folder(ga_avatar, tmp_path, heavy, seed):
    """flame_param.npz (arrays reshaped, retyped, pickled, headers lying, bytes) and point_cloud.ply (header lines,
    bytes) of a GaussianAvatars avatar: read_flame_params and read_bound_gaussians load or refuse with
    ImportFormatError naming the file."""
    from gaussiantalker.exporter.imports.sources.gaussian_avatars import read_bound_gaussians, read_flame_params

    arrays, written = ga_avatar["arrays"], ga_avatar["written"]
    ply = written["ply_path"].read_bytes()
    params = ga_avatar["params"]

    def make(rng: np.random.Generator, index: int) -> Case:
        if index % 2:
            path = tmp_path / "point_cloud.ply"
            changed, what = _ply_header_mutation(ply, rng) if rng.random() < 0.5 else mutate_bytes(ply, rng)
        else:
            path = tmp_path / "flame_param.npz"
            changed, what = _mutated_npz(params, rng, arrays_below=0.6, zip_below=0.8)
        path.write_bytes(changed)
        return Case(what, path, str(path))

    def read(path: Path) -> None:
        if path.suffix == ".ply":
            read_bound_gaussians(path, arrays.n_faces)
        else:
            read_flame_params(path, arrays.n_vertices, 25.0)

    fuzz(read, make, _counts(300, heavy), seed + 3, ImportFormatError)


@pytest.mark.parametrize("heavy, seed", RUNS)
def test_fuzz_gaussian_avatars_import(ga_avatar, tmp_path, heavy, seed):
    """The whole import on a few mutated avatars (it builds a speaker, ~0.4 s a case), folder layout included:
    iteration folders that are files, odd iteration numbers, a PLY that is a folder."""
    from gaussiantalker.exporter.imports.sources.gaussian_avatars import GaussianAvatarsOptions, import_gaussian_avatars

    written, arrays = ga_avatar["written"], ga_avatar["arrays"]
    ply, params = written["ply_path"].read_bytes(), written["param_path"].read_bytes()

    def make(rng: np.random.Generator, index: int) -> Case:
        root = tmp_path / f"case{index}"
        folder = root / "point_cloud" / f"iteration_{[30000, 0, 10**30, 7][int(rng.integers(4))]}"
        folder.mkdir(parents=True)
        kind = int(rng.integers(5))
        what = "valid"
        (folder / "point_cloud.ply").write_bytes(ply)
        (folder / "flame_param.npz").write_bytes(params)
        if kind == 0:
            changed, what = _ply_header_mutation(ply, rng)
            (folder / "point_cloud.ply").write_bytes(changed)
        elif kind == 1:
            changed, what = mutate_npz_arrays(ga_avatar["params"], rng)
            (folder / "flame_param.npz").write_bytes(changed)
        elif kind == 2:
            (folder / "point_cloud.ply").unlink()
            (folder / "point_cloud.ply").mkdir()
            what = "point_cloud.ply is a folder"
        elif kind == 3:
            (root / "point_cloud" / "iteration_99").write_bytes(b"not a folder")
            (folder / "flame_param.npz").unlink()
            (folder / "flame_param.npz").mkdir()
            what = "an iteration file; flame_param.npz a folder"
        return Case(f"{folder.name}: {what}", root, str(root))

    def read(root: Path) -> None:
        import_gaussian_avatars(root, arrays, GaussianAvatarsOptions())

    fuzz(read, make, _counts(12, heavy), seed + 4, ImportFormatError)


# -- FLAME npz ----------------------------------------------------------------------------------------------------


def _small_flame() -> dict[str, np.ndarray]:
    """A FLAME-layout model of 12 vertices (load_flame_npz reads any vertex count)."""
    rng = np.random.default_rng(5)
    weights = rng.random((12, 5))
    return {"v_template": rng.normal(size=(12, 3)), "f": rng.integers(0, 12, (10, 3)).astype(np.uint32),
            "shapedirs": rng.normal(size=(12, 3, 10)) * 1e-3, "posedirs": rng.normal(size=(12, 3, 36)) * 1e-3,
            "J_regressor": np.full((5, 12), 1 / 12), "weights": weights / weights.sum(1, keepdims=True),
            "kintree_table": np.array([[2**32 - 1, 0, 1, 1, 1], [0, 1, 2, 3, 4]], np.int64),
            "flame_version": np.array("2023"), "n_shape": np.int64(6)}


@pytest.mark.parametrize("heavy, seed", RUNS)
def test_fuzz_flame_npz(tmp_path, heavy, seed):
    """load_flame_npz (the SDK's FLAME npz) on a small FLAME-layout npz with its arrays and npy headers mutated, its
    zip fields and bytes: loads or CheckpointError naming the file; never unpickles."""
    from gaussiantalker.exporter.model.flame_npz import load_flame_npz

    model = _small_flame()

    def make(rng: np.random.Generator, index: int) -> Case:
        path = tmp_path / "flame.npz"
        choice = rng.random()
        if choice < 0.6:
            changed, what = mutate_npz_arrays(model, rng)
        elif choice < 0.8:
            changed, what = mutate_zip_field(npz_bytes(model, compressed=bool(index % 2)), rng)
        else:
            changed, what = mutate_bytes(npz_bytes(model, compressed=bool(index % 2)), rng)
        path.write_bytes(changed)
        return Case(what, path, str(path))

    fuzz(lambda path: load_flame_npz(path, 4, 4, shape_columns=6), make, _counts(250, heavy), seed + 5,
         CheckpointError)


@pytest.mark.parametrize("heavy, seed", RUNS)
def test_fuzz_gaussian_avatars_flame_npz(ga_avatar, tmp_path, heavy, seed):
    """load_gaussian_avatars_flame on the full-size synthetic FLAME npz (53 MB): its version and column records
    and its zip fields mutated (the array checks are load_flame_npz's, fuzzed above)."""
    from gaussiantalker.exporter.imports.sources.gaussian_avatars_flame import load_gaussian_avatars_flame

    data = ga_avatar["flame_path"].read_bytes()
    with zipfile.ZipFile(ga_avatar["flame_path"]) as archive:
        entries = [(info.filename, archive.read(info)) for info in archive.infolist()]

    def make(rng: np.random.Generator, index: int) -> Case:
        path = tmp_path / "flame.npz"
        kind = int(rng.integers(3))
        if kind == 0:
            changed, what = mutate_zip_field(data, rng)
        elif kind == 1:
            extra = {"flame_version": [np.array("2020"), np.array(["a", "b"]), np.array(3.5), np.array(b"2023")],
                     "n_shape": [np.array("x"), np.float64(np.nan), np.array([300, 300]), np.uint64(2**64 - 1)],
                     "n_expr": [np.array(-1), np.array(1e300)]}
            key = list(extra)[int(rng.integers(3))]
            value = extra[key][int(rng.integers(len(extra[key])))]
            changed = write_zip(entries + [(f"{key}.npy", _npy(value))])
            what = f"{key} = {value!r}"
        else:
            changed, what = mutate_bytes(data[:4096], rng)
            changed += data[4096:]
        path.write_bytes(changed)
        return Case(what, path, str(path))

    fuzz(load_gaussian_avatars_flame, make, _counts(6, heavy), seed + 6, GaussianTalkerError)


def _npy(value) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, np.asarray(value), allow_pickle=False)
    return buffer.getvalue()


# -- motion files ------------------------------------------------------------------------------------------------


def motion_documents() -> list[dict]:
    """LAM motion JSON of each kind the loader reads: bsData.json's layout, {name: weight} frames, named weights
    with times and a head pose."""
    from lam_avatars import motion_json

    from gaussiantalker.sdk.rig import ARKIT_BLENDSHAPES

    return [motion_json(), {"frames": [{"jawOpen": 0.5, "eyeBlinkLeft": 1.0}] * 5},
            {"names": list(ARKIT_BLENDSHAPES[:3]), "frames": [{"weights": [0.1, 0.2, 0.3], "time": t / 30}
                                                              for t in range(6)], "head_pose": [[0, 0, 0]]}]


def mutated_motion(document: dict, rng: np.random.Generator) -> tuple[bytes, str]:
    """One seeded mutation of a motion document's JSON values (3 in 4) or of its bytes, and what was done."""
    if rng.random() < 0.75:
        changed, what = mutate_json(document, rng)
        return dumps(changed), what
    return mutate_bytes(json.dumps(document).encode(), rng)


@pytest.mark.parametrize("heavy, seed", RUNS)
def test_fuzz_arkit_motion_json(tmp_path, heavy, seed):
    """LAM motion JSON (bsData.json's layout; LAM_WebRender's and {name: weight} frames too) with values swapped
    for huge numbers, wrong types, deep nesting, and bytes mutated: the runtime's motion loader (the path a
    `motion=` argument takes) loads or refuses with DriveError naming the file."""
    from gaussiantalker.runtime.motions import arkit_motion

    documents = motion_documents()

    def make(rng: np.random.Generator, index: int) -> Case:
        path = tmp_path / "motion.json"
        data, what = mutated_motion(documents[index % len(documents)], rng)
        path.write_bytes(data)
        return Case(what, path, str(path))

    fuzz(lambda path: arkit_motion(path, None, 30, "speaker"), make, _counts(300, heavy), seed + 7, DriveError)


@pytest.mark.parametrize("heavy, seed", RUNS)
def test_fuzz_flame_motion_npz(ga_avatar, tmp_path, heavy, seed):
    """GaussianAvatars' flame_param.npz as a motion file (its per-frame keys) mutated: the runtime's FLAME motion
    loader loads or refuses with DriveError naming the file."""
    from gaussiantalker.runtime.motions import flame_motion

    params = {key: value for key, value in ga_avatar["params"].items() if key != "dynamic_offset"}

    def make(rng: np.random.Generator, index: int) -> Case:
        path = tmp_path / "motion.npz"
        changed, what = _mutated_npz(params, rng, arrays_below=0.7, zip_below=0.85)
        path.write_bytes(changed)
        return Case(what, path, str(path))

    fuzz(lambda path: flame_motion(path, None, 25, 100, "speaker"), make, _counts(300, heavy), seed + 8, DriveError)


# -- bundles ------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_bundle(tmp_path_factory) -> bytes:
    """A bundle with a buffer in every codec, four sparse ones (one with its mask deflated, one a codebook), buffers
    stored deflated (a codebook's, a quantised one's), and a compressed and a stored graph."""
    from gaussiantalker.sdk.bundle import BundleWriter

    rng = np.random.default_rng(3)
    writer = BundleWriter({"speaker": {"n_expr": 3}, "camera": {"width": 4}})
    values = rng.normal(size=(6, 50)).astype(np.float32)
    for codec in ("raw", "fp16", "q16", "q8", "q4"):
        writer.add_buffer(f"w/{codec}", values, codec=codec, chunk=16 if codec.startswith("q") else None)
    writer.add_buffer("ids", np.arange(300, dtype=np.int64), codec="index")
    mostly_zero = np.where(rng.random((6, 50)) < 0.8, 0.0, values).astype(np.float32)
    writer.add_buffer("w/sparse_raw", mostly_zero, codec="raw", sparse=True)
    writer.add_buffer("w/sparse_q8", mostly_zero, codec="q8", chunk=16, sparse=True)
    runs = np.zeros((4, 400), np.float32)  # a morph basis's kind: one run per row, so its mask is stored deflated
    for row, start in enumerate((0, 90, 250, 300)):
        runs[row, start: start + 100] = values[row, :50].repeat(2)
    writer.add_buffer("w/sparse_runs", runs, codec="q8", chunk=16, sparse=True)
    writer.add_buffer("raw_ids", np.arange(7, dtype=np.int32))
    writer.add_buffer("w/vq", values, codec="vq", chunk=12)  # 4-bit indices, 2 of them a byte
    writer.add_buffer("w/vq_sparse", mostly_zero, codec="vq", chunk=5, sparse=True)
    writer.add_buffer("w/vq_zlib", np.tile(values[:, :10], 40), codec="vq", chunk=3, compress=True)
    writer.add_buffer("w/q8_zlib", runs, codec="q8", chunk=16, compress=True)
    io_spec = [{"name": "x", "dtype": "float32", "shape": [1, "n"]}]
    writer.add_graph("g", b"\x08\x07" + bytes(200), io_spec, io_spec, {"w": "w/q8"})
    writer.add_graph("h", b"\x08\x07graph", io_spec, [], {"i": "ids"}, compress=False)
    path = tmp_path_factory.mktemp("fuzz_bundle") / "small.gtb"
    writer.write(path)
    return path.read_bytes()


def _bundle_with_manifest(data: bytes, manifest: bytes) -> bytes:
    """The bundle's payload under another manifest, with the header's length and digest made to match it."""
    import hashlib

    from gaussiantalker.sdk.bundle import _HEADER, HEADER_SIZE, MAGIC, _align

    length = struct.unpack_from("<Q", data, 16)[0]
    payload = data[HEADER_SIZE + _align(length):]
    header = _HEADER.pack(MAGIC, *struct.unpack_from("<HH", data, 8), 0, len(manifest),
                          hashlib.sha256(manifest).digest())  # the bundle's own format version
    header += b"\0" * (HEADER_SIZE - len(header))
    return header + manifest + b"\0" * (_align(len(manifest)) - len(manifest)) + payload


def bundle_manifest(data: bytes) -> dict:
    """The parsed manifest of a bundle's bytes."""
    from gaussiantalker.sdk.bundle import HEADER_SIZE

    length = struct.unpack_from("<Q", data, 16)[0]
    return json.loads(data[HEADER_SIZE:HEADER_SIZE + length])


def mutated_bundle(data: bytes, manifest: dict, rng: np.random.Generator) -> tuple[bytes, str]:
    """One seeded mutation of a bundle and what was done: a manifest value swapped under a matching digest (so
    the checks behind it run), a header field set to 0/-1/huge, or bytes anywhere."""
    choice = rng.random()
    if choice < 0.55:
        changed, what = mutate_json(manifest, rng)
        return _bundle_with_manifest(data, dumps(changed)), what
    if choice < 0.7:
        return mutate_field_bytes(data, rng, [(8, 2), (10, 2), (12, 4), (16, 8), (56, 8)])
    return mutate_bytes(data, rng)


@pytest.mark.parametrize("heavy, seed", RUNS)
def test_fuzz_bundle(small_bundle, tmp_path, heavy, seed):
    """The bundle reader (Bundle, then every graph and buffer read and decoded) on header fields set to 0/-1/huge,
    bytes mutated anywhere, and manifest values swapped (with a matching digest, so the checks behind it run):
    loads or BundleError naming the file."""
    from gaussiantalker.sdk.bundle import Bundle

    manifest = bundle_manifest(small_bundle)

    def make(rng: np.random.Generator, index: int) -> Case:
        path = tmp_path / "case.gtb"
        data, what = mutated_bundle(small_bundle, manifest, rng)
        path.write_bytes(data)
        return Case(what, path, str(path))

    def read(path: Path) -> None:
        bundle = Bundle(path)
        bundle.verify_all()
        for name in bundle.manifest["buffers"]:
            bundle.buffer(name)

    fuzz(read, make, _counts(400, heavy), seed + 9, BundleError)


def _relayout(manifest: dict, blobs: dict[tuple[str, str], bytes]) -> bytes:
    """A bundle of `manifest` whose entries hold `blobs` ((kind, name) -> stored bytes), offsets, sizes, checksums
    and payload_size recomputed: a well-formed file around whatever the entries hold."""
    import hashlib

    from gaussiantalker.sdk.bundle import _HEADER, HEADER_SIZE, MAGIC, _align

    payload = bytearray()
    for (kind, name), blob in blobs.items():
        manifest[kind][name].update(offset=len(payload), nbytes=len(blob), sha256=hashlib.sha256(blob).hexdigest())
        payload += blob + b"\0" * (_align(len(blob)) - len(blob))
    manifest["payload_size"] = len(payload)
    text = dumps(manifest)
    header = _HEADER.pack(MAGIC, *manifest["version"], 0, len(text), hashlib.sha256(text).digest())
    header += b"\0" * (HEADER_SIZE - len(header))
    return header + text + b"\0" * (_align(len(text)) - len(text)) + bytes(payload)


@pytest.fixture(scope="module")
def lam_bundle(lam_members, tmp_path_factory) -> Path:
    """A LAM avatar's fp32 bundle (an ARKit speaker with a pose and a motion track)."""
    from lam_avatars import write_avatar_zip

    from gaussiantalker.exporter.export.bundle_export import export_bundle
    from gaussiantalker.exporter.imports.sources.lam import import_lam

    root = tmp_path_factory.mktemp("fuzz_head")
    path = root / "avatar.gtb"
    export_bundle(import_lam(write_avatar_zip(root / "avatar.zip"), progress=False), path, progress=False)
    return path


@pytest.mark.heavy
def test_fuzz_talking_head(lam_bundle, tmp_path):
    """TalkingHead (the runtime's whole load: the manifest's sections, the graph checks, onnxruntime sessions, one
    frame drawn) on a LAM avatar's bundle whose manifest values or graph bytes are mutated, every checksum made to
    match: loads and draws, or raises the SDK's error naming the file. Heavy only (~0.2 s a case)."""
    import zlib

    from gaussiantalker.runtime import TalkingHead
    from gaussiantalker.sdk.bundle import Bundle

    bundle = Bundle(lam_bundle)
    manifest = json.loads(json.dumps(bundle.manifest))
    blobs = {(kind, name): bundle._read_entry(name, entry) for kind in ("graphs", "buffers")
             for name, entry in manifest[kind].items()}
    sections = [key for key in manifest if key not in ("graphs", "buffers", "payload_size", "format", "version")]

    def make(rng: np.random.Generator, index: int) -> Case:
        path = tmp_path / "case.gtb"
        edited, stored = json.loads(json.dumps(manifest)), dict(blobs)
        choice = rng.random()
        if choice < 0.4:
            key = sections[int(rng.integers(len(sections)))]
            value, what = mutate_json({"v": edited[key]}, rng)
            if "v" in value:
                edited[key] = value["v"]
            else:
                del edited[key]
            what = f"{key}: {what}"
        elif choice < 0.6:
            kind = ["graphs", "buffers"][int(rng.integers(2))]
            name = list(edited[kind])[int(rng.integers(len(edited[kind])))]
            entry = {k: v for k, v in edited[kind][name].items() if k not in ("offset", "nbytes", "sha256")}
            value, what = mutate_json(entry, rng)
            edited[kind][name] = {**edited[kind][name], **value}
            for key in set(entry) - set(value):
                del edited[kind][name][key]
            what = f"{kind} {name}: {what}"
        else:
            name = list(edited["graphs"])[int(rng.integers(len(edited["graphs"])))]
            onnx_bytes, what = mutate_bytes(zlib.decompress(blobs[("graphs", name)]), rng)
            stored[("graphs", name)] = zlib.compress(onnx_bytes)
            edited["graphs"][name]["raw_nbytes"] = len(onnx_bytes)
            what = f"graph {name}: {what}"
        path.write_bytes(_relayout(edited, stored))
        return Case(what, path, str(path))

    def read(path: Path) -> None:
        with TalkingHead(path, resolution=(48, 48)) as head:
            head.render_blendshapes({"jawOpen": 0.5})

    fuzz(read, make, 300, 2000, GaussianTalkerError)


# -- checkpoints --------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory, lam_members) -> list[Path]:
    """A FLAME speaker's checkpoint (200 Gaussians, untrained translator) and a LAM avatar's (an ARKit speaker)."""
    from lam_avatars import write_avatar_zip

    from gaussiantalker.exporter.demo.demo_speaker import make_demo_speaker
    from gaussiantalker.exporter.export.checkpoint import save_checkpoint
    from gaussiantalker.exporter.imports.sources.lam import import_lam

    root = tmp_path_factory.mktemp("fuzz_ckpt")
    speaker, _ = make_demo_speaker(n_gaussians=200, train_seconds=0, progress=False)
    avatar = import_lam(write_avatar_zip(root / "avatar.zip"), progress=False)
    return [save_checkpoint(speaker, root / "flame.ckpt"), save_checkpoint(avatar, root / "arkit.ckpt")]


def _mutate_payload(payload: dict, rng: np.random.Generator) -> tuple[dict, str]:
    """A checkpoint payload with one leaf replaced: another shape, dtype or type, non-finite, huge, or removed."""
    import torch

    paths, stack = [], [((), payload)]
    while stack:
        path, value = stack.pop()
        if isinstance(value, dict):
            stack += [((*path, key), item) for key, item in value.items()]
        paths.append(path)
    path = paths[int(rng.integers(1, len(paths)))]
    parent = payload
    for key in path[:-1]:
        parent = parent[key]
    current = parent[path[-1]]
    options = [None, "x", -1, 10**30, float("nan"), [1, 2], {"a": 1}, torch.zeros(0), torch.zeros(3, 3, 3),
               torch.full((2,), float("inf")), torch.ones(5, dtype=torch.int64) * 2**40, True]
    if isinstance(current, torch.Tensor):
        options += [current.double(), current.reshape(-1), current.flip(0) if current.ndim else current,
                    current[: max(current.shape[0] - 1, 0)] if current.ndim else current, current.to(torch.int8),
                    current * 1e30, torch.cat([current, current]) if current.ndim else current]
    choice = int(rng.integers(len(options) + 1))
    if choice == len(options):
        del parent[path[-1]]
        return payload, f"dropped {'/'.join(map(str, path))}"
    parent[path[-1]] = options[choice]
    return payload, f"{'/'.join(map(str, path))} = {str(options[choice])[:40]}"


@pytest.mark.parametrize("heavy, seed", RUNS)
def test_fuzz_checkpoint(checkpoints, tmp_path, heavy, seed):
    """load_checkpoint on a FLAME and an ARKit speaker's checkpoint with entries replaced (wrong shapes, dtypes,
    types, non-finite or huge values, removed) and with bytes and zip fields mutated: loads or CheckpointError
    naming the file (torch.load always weights_only)."""
    import torch

    from gaussiantalker.exporter.export.checkpoint import load_checkpoint

    raw = [path.read_bytes() for path in checkpoints]

    def make(rng: np.random.Generator, index: int) -> Case:
        path = tmp_path / "case.ckpt"
        which = index % 2
        choice = rng.random()
        if choice < 0.6:
            payload, what = _mutate_payload(torch.load(checkpoints[which], weights_only=True), rng)
            torch.save(payload, path)
        else:
            data, what = mutate_zip_field(raw[which], rng) if choice < 0.8 else mutate_bytes(raw[which], rng)
            path.write_bytes(data)
        return Case(f"{checkpoints[which].name}: {what}", path, str(path))

    for path in checkpoints:  # both load as written
        load_checkpoint(path)
    fuzz(load_checkpoint, make, _counts(60, heavy), seed + 10, CheckpointError)


# -- audio models -------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def audio_model(tmp_path_factory) -> bytes:
    from lam_avatars import energy_audio_model

    return energy_audio_model(tmp_path_factory.mktemp("fuzz_audio") / "energy.onnx", frame_samples=64).read_bytes()


def _mutate_onnx(data: bytes, rng: np.random.Generator) -> tuple[bytes, str]:
    """An ONNX model with a type, a shape, an input or output, or a tensor's data location changed."""
    import onnx

    model = onnx.load_from_string(data)
    graph = model.graph
    kind = int(rng.integers(6))
    if kind == 0:
        value = [graph.input[0], graph.output[0]][int(rng.integers(2))]
        value.type.tensor_type.elem_type = int(rng.integers(0, 17))
        what = f"{value.name} elem_type {value.type.tensor_type.elem_type}"
    elif kind == 1:
        value = [graph.input[0], graph.output[0]][int(rng.integers(2))]
        dim = value.type.tensor_type.shape.dim.add()
        dim.dim_value = int(rng.integers(0, 2**40))
        what = f"{value.name} gains a dimension"
    elif kind == 2:
        del graph.output[:]
        what = "no outputs"
    elif kind == 3:
        graph.input.add().CopyFrom(graph.input[0])
        graph.input[-1].name = "second"
        what = "a second input"
    elif kind == 4:
        tensor = graph.initializer[int(rng.integers(len(graph.initializer)))]
        tensor.ClearField("raw_data")
        tensor.data_location = onnx.TensorProto.EXTERNAL
        entry = tensor.external_data.add()
        entry.key, entry.value = "location", ["../secret.bin", "/etc/hostname", "link.bin", "sub/../../x",
                                              "missing.bin", "data.bin"][int(rng.integers(6))]
        for key, value in (("offset", str(int(rng.integers(-5, 2**40)))), ("length", str(int(rng.integers(0, 99))))):
            if rng.random() < 0.5:
                extra = tensor.external_data.add()
                extra.key, extra.value = key, value
        what = f"{tensor.name} data in {entry.value!r}"
    else:
        graph.node[int(rng.integers(len(graph.node)))].op_type = ["Nope", "", "Conv", "Loop"][int(rng.integers(4))]
        what = "a node's operator changed"
    return model.SerializeToString(), what


@pytest.mark.parametrize("heavy, seed", RUNS)
def test_fuzz_audio_model(audio_model, tmp_path, heavy, seed):
    """load_audio_model (gt-import --audio-model) on an ONNX model's bytes mutated and its signature, operators
    and tensor data locations changed (paths out of its folder, links, missing files): loads or ImportFormatError
    naming the file, and never reads a file outside the model's folder."""
    from gaussiantalker.exporter.imports.audio_model import load_audio_model

    folder = tmp_path / "models"
    folder.mkdir()
    (tmp_path / "secret.bin").write_bytes(b"SECRET" * 100)
    (folder / "data.bin").write_bytes(b"\0" * 64)
    os.symlink(tmp_path / "secret.bin", folder / "link.bin")

    def make(rng: np.random.Generator, index: int) -> Case:
        path = folder / "model.onnx"
        changed, what = _mutate_onnx(audio_model, rng) if rng.random() < 0.5 else \
            mutate_bytes(audio_model, rng)
        path.write_bytes(changed)
        return Case(what, path, str(path))

    def read(path: Path) -> None:
        assert b"SECRET" not in load_audio_model(path)

    fuzz(read, make, _counts(150, heavy), seed + 11, ImportFormatError)


# -- the CLI ------------------------------------------------------------------------------------------------------


def test_cli_refusals_are_one_line_naming_the_file(lam_members, ga_avatar, tmp_path):
    """`gt-import lam` and `gt-import gaussian-avatars` on fuzzed files they refuse: exit status 2 and one line
    `error: ...` naming the file (in process)."""
    from typer.testing import CliRunner

    from gaussiantalker.cli.imports import app

    runner = CliRunner()
    rng = np.random.default_rng(12)
    make_lam = _lam_zip_case(lam_members, tmp_path)
    refused = 0
    for index in range(8):
        case = make_lam(rng, index)
        result = runner.invoke(app, ["lam", str(case.argument), "-o", str(tmp_path / "out.ckpt"), "-q"])
        if result.exit_code == 0:
            continue
        refused += 1
        lines = result.stderr.splitlines()
        assert result.exit_code == 2 and len(lines) == 1 and lines[0].startswith("error: ") and \
            str(case.argument) in lines[0], (case.what, result.exit_code, result.stderr, result.stdout)
    folder = tmp_path / "ga" / "point_cloud" / "iteration_1"
    folder.mkdir(parents=True)
    ply = ga_avatar["written"]["ply_path"].read_bytes()
    (folder / "flame_param.npz").write_bytes(ga_avatar["written"]["param_path"].read_bytes())
    for _ in range(4):
        changed, what = _ply_header_mutation(ply, rng)
        (folder / "point_cloud.ply").write_bytes(changed)
        result = runner.invoke(app, ["gaussian-avatars", str(tmp_path / "ga"), "--flame",
                                     str(ga_avatar["flame_path"]), "-o", str(tmp_path / "ga.ckpt")])
        if result.exit_code == 0:
            continue
        refused += 1
        lines = result.stderr.splitlines()
        assert result.exit_code == 2 and len(lines) == 1 and lines[0].startswith("error: ") and \
            str(folder / "point_cloud.ply") in lines[0], (what, result.exit_code, result.stderr)
    assert refused >= 6


# -- the holes the fuzz found, one case each ----------------------------------------------------------------------


def _lam_zip_with(lam_members: dict[str, bytes], path: Path, member: str, data: bytes) -> Path:
    path.write_bytes(write_zip([(n, data if n.endswith(member) else d) for n, d in lam_members.items()]))
    return path


def _glb_edit(lam_members: dict[str, bytes], name: str, edit: Callable[[dict], None]) -> bytes:
    doc, rest = glb_split(lam_members[f"avatar/{name}"])
    edit(doc)
    return glb_join(dumps(doc), rest)


LAM_HOLES = {
    "glTF JSON nested 100,000 deep": ("skin.glb", lambda m: glb_join(b"[" * 100_000 + b"]" * 100_000, b""),
                                      "nests too deep"),
    "glTF integer of 5,000 digits": ("skin.glb", lambda m: glb_join(b'{"asset": ' + b"9" * 5000 + b"}", b""),
                                     "is not JSON"),
    "zero accessor of 10^12 rows": ("skin.glb", lambda m: _glb_edit(m, "skin.glb", lambda d: d["accessors"][0].update(
        count=10**12)), "claims 1000000000000 rows without a bufferView"),
    "mesh that is a number": ("skin.glb", lambda m: _glb_edit(m, "skin.glb", lambda d: d.update(meshes=[7])),
                              "mesh 0 must be an object"),
    "child with two parents": ("skin.glb", lambda m: _glb_edit(m, "skin.glb", lambda d: d["nodes"][4].update(
        children=[2])), "node 2 has two parents"),
    "zero scale on the head's chain": ("skin.glb", lambda m: _glb_edit(m, "skin.glb", lambda d: d["nodes"][2].update(
        scale=[0, 0, 0])), "rest transform is degenerate"),
    "clip of 10^9 seconds": ("animation.glb", lambda m: _clip_time(m, 1e9), "lasts 1e+09 s"),
    "PLY of 10^12 vertices": ("offset.ply", lambda m: re.sub(rb"element vertex \d+", b"element vertex 1000000000000",
                                                             m["avatar/offset.ply"], count=1),
                              "declares 1000000000000 'vertex' rows"),
    "PLY field f_rest_x": ("offset.ply", lambda m: m["avatar/offset.ply"].replace(b"property float nz",
                                                                                b"property float f_rest_x"),
                           "f_rest fields must be f_rest_0"),
    "bsData fps 10^-9": ("bsData.json", lambda m: m["avatar/bsData.json"].replace(b'"fps": 30.0', b'"fps": 1e-9'),
                         "over the 524288 frame limit"),
    "bsData weight 10^400": ("bsData.json", lambda m: m["avatar/bsData.json"].replace(
        b'"weights": [0.0', b'"weights": [1' + b"0" * 400, 1), "must be numbers"),
    "vertex_order of lists": ("vertex_order.json", lambda m: b"[[1]" + b", 1" * (_ply_rows(m) - 1) + b"]",
                              "vertex indices"),
}


def _ply_rows(members: dict[str, bytes]) -> int:
    """The avatar's vertex count, as its offset.ply declares it."""
    return int(re.search(rb"element vertex (\d+)", members["avatar/offset.ply"]).group(1))


def _clip_time(members: dict[str, bytes], seconds: float) -> bytes:
    """animation.glb with its first clip's last key time set to `seconds` (the float32 in the binary chunk)."""
    data = bytearray(members["avatar/animation.glb"])
    doc, rest = glb_split(bytes(data))
    view = doc["bufferViews"][doc["accessors"][doc["animations"][0]["samplers"][0]["input"]]["bufferView"]]
    at = len(data) - len(rest) + 8 + view["byteOffset"] + view["byteLength"] - 4
    data[at:at + 4] = struct.pack("<f", seconds)
    return bytes(data)


@pytest.mark.parametrize("case", list(LAM_HOLES))
def test_lam_hole(lam_members, tmp_path, case):
    """Each hole the fuzz found in the LAM reader, as one file: ImportFormatError naming the zip and the problem."""
    from gaussiantalker.exporter.imports.sources.lam import import_lam

    member, make, words = LAM_HOLES[case]
    path = _lam_zip_with(lam_members, tmp_path / "hole.zip", member, make(lam_members))
    with pytest.raises(ImportFormatError) as error:
        import_lam(path, progress=False)
    assert str(path) in str(error.value) and words in str(error.value), str(error.value)


def test_zip_holes(lam_members, tmp_path):
    """Member names out of the folder, a member twice, a bzip2 bomb, a stated size over the budget, an encrypted
    member, an unknown method: each refused by name before anything is inflated."""
    from gaussiantalker.exporter.imports.sources.lam import import_lam

    items = list(lam_members.items())
    cases = {"../skin.glb": write_zip([("../skin.glb", b"x")] + items),
             "avatar\\\\skin.glb": write_zip([("avatar\\skin.glb", b"x")] + items),
             "C:/": write_zip([("C:/avatar/skin.glb", b"x")] + items),
             "holds avatar/skin.glb twice": write_zip(items + [("avatar/skin.glb", b"x")])}
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name, data in items:
            archive.writestr(name, bytes(200 << 20) if name.endswith("skin.glb") else data,
                             compress_type=zipfile.ZIP_BZIP2 if name.endswith("skin.glb") else zipfile.ZIP_STORED)
    cases["more than 1100 times as many"] = buffer.getvalue()
    plain = write_zip(items)
    skin = plain.index(b"PK\x01\x02", plain.index(b"avatar/skin.glb", plain.index(b"PK\x01\x02")) - 46)
    for words, offset, size, value in (("over the", 24, 4, 0xFFFFFFFF), ("is encrypted", 8, 2, 1),
                                       ("compression method 99", 10, 2, 99)):
        data = bytearray(plain)  # the central directory record of avatar/skin.glb
        data[skin + offset:skin + offset + size] = value.to_bytes(size, "little")
        cases[words] = bytes(data)
    for words, data in cases.items():
        path = tmp_path / "hole.zip"
        path.write_bytes(data)
        tracemalloc.start()
        with pytest.raises(ImportFormatError) as error:
            import_lam(path, progress=False)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert str(path) in str(error.value) and words in str(error.value), (words, str(error.value))
        assert peak < 64 << 20, (words, peak)


def test_npz_and_motion_holes(tmp_path):
    """An npy header claiming 10^10 rows, a pickled object array, a file that is one .npy array (np.load would read
    it, or unpickle a pickle): refused before anything is allocated or unpickled."""
    from fuzz_mutations import npy_bytes

    from gaussiantalker.sdk.flame_motion import load_flame_motion
    from gaussiantalker.sdk.motion import load_motion

    cases = {"more than the member's": write_zip([("expr.npy", npy_bytes("<f8", "(10000000000, 100)", b"\0" * 800))]),
             "never pickled objects": npz_bytes({"expr": np.array([None, {}], dtype=object)}),
             "is one array": _npy(np.zeros((3, 100))),
             "not an npz (zip) file": b"\x80\x04\x95" + bytes(20)}
    for words, data in cases.items():
        path = tmp_path / "motion.npz"
        path.write_bytes(data)
        with pytest.raises(DriveError, match=words.replace("(", r"\(").replace(")", r"\)")):
            load_flame_motion(path, 25.0)
    path = tmp_path / "motion.json"
    path.write_bytes(b'{"frames": [' + b"[" * 50_000 + b"]" * 50_000 + b"]}")
    with pytest.raises(DriveError, match="nests too deep"):
        load_motion(path)


def test_audio_model_data_outside_its_folder_is_never_read(audio_model, tmp_path):
    """A tensor whose external data is a file outside the model's folder (a secret the model would copy into every
    checkpoint and bundle): refused by name, whichever way the path leads out."""
    import onnx

    from gaussiantalker.exporter.imports.audio_model import load_audio_model

    folder = tmp_path / "models"
    folder.mkdir()
    (tmp_path / "secret.bin").write_bytes(b"SECRET" * 100)
    os.symlink(tmp_path / "secret.bin", folder / "link.bin")
    for location in ("../secret.bin", str(tmp_path / "secret.bin"), "link.bin", "sub/../../secret.bin"):
        model = onnx.load_from_string(audio_model)
        tensor = model.graph.initializer[0]
        tensor.ClearField("raw_data")
        tensor.data_location = onnx.TensorProto.EXTERNAL
        entry = tensor.external_data.add()
        entry.key, entry.value = "location", location
        path = folder / "model.onnx"
        path.write_bytes(model.SerializeToString())
        with pytest.raises(ImportFormatError, match="which is not a file inside the model's folder"):
            load_audio_model(path)


# -- the holes the TalkingHead fuzz found, one file each ----------------------------------------------------------


def _pb_varint(value: int) -> bytes:
    out = bytearray()
    while True:
        out.append((value & 0x7F) | (0x80 if value > 0x7F else 0))
        value >>= 7
        if not value:
            return bytes(out)


def _pb_field(number: int, payload: bytes) -> bytes:
    """One length-delimited protobuf field."""
    return _pb_varint(number << 3 | 2) + _pb_varint(len(payload)) + payload


def _head_bundle(lam_bundle: Path, path: Path, edit: Callable[[dict], None] = lambda manifest: None,
                 deform_tail: bytes = b"") -> Path:
    """The LAM avatar's bundle with its manifest edited and `deform_tail` appended to its deform graph (protobuf
    merges a second ModelProto field into the first), every checksum made to match."""
    import zlib

    from gaussiantalker.sdk.bundle import Bundle

    bundle = Bundle(lam_bundle)
    manifest = json.loads(json.dumps(bundle.manifest))
    blobs = {(kind, name): bundle._read_entry(name, entry) for kind in ("graphs", "buffers")
             for name, entry in manifest[kind].items()}
    if deform_tail:
        onnx_bytes = zlib.decompress(blobs[("graphs", "deform")]) + deform_tail
        blobs[("graphs", "deform")] = zlib.compress(onnx_bytes)
        manifest["graphs"]["deform"]["raw_nbytes"] = len(onnx_bytes)
    edit(manifest)
    path.write_bytes(_relayout(manifest, blobs))
    return path


def _head_refusal(path: Path, error: type[Exception] = BundleError) -> str:
    """TalkingHead's refusal of `path`: one line naming the file (returned for the case's own words)."""
    from gaussiantalker.runtime import TalkingHead

    with pytest.raises(error) as refused:
        TalkingHead(path, resolution=(48, 48))
    text = str(refused.value)
    assert "\n" not in text and str(path) in text and len(text) < len(str(path)) + 500, text
    return text


def test_graph_of_nested_subgraphs_is_refused_by_name(lam_bundle, tmp_path):
    """An 18 KB graph of subgraphs nested 3,000 deep (graph > node > attribute > graph ...): the protobuf walk
    refuses it by name past MAX_MESSAGE_DEPTH instead of raising RecursionError."""
    from gaussiantalker.runtime.onnx_wire import MAX_MESSAGE_DEPTH

    graph = b""
    for _ in range(3000):
        graph = _pb_field(1, _pb_field(5, _pb_field(6, graph)))  # GraphProto.node > .attribute > .g
    tail = _pb_field(7, graph)  # ModelProto.graph
    assert 16_000 < len(tail) < 32_000
    text = _head_refusal(_head_bundle(lam_bundle, tmp_path / "nested.gtb", deform_tail=tail))
    assert f"graph 'deform' is not a valid ONNX model (its messages nest more than {MAX_MESSAGE_DEPTH} deep" in text


def test_graph_nested_within_protobufs_limit_is_walked(lam_bundle):
    """Subgraphs nested 33 deep (99 messages below the model, within protobuf's own limit) are walked, not refused:
    the depth limit refuses nothing a protobuf parser would load."""
    import zlib

    from gaussiantalker.runtime.onnx_wire import model_tensors
    from gaussiantalker.sdk.bundle import Bundle

    graph = _pb_field(5, _pb_varint(1 << 3) + _pb_varint(4) + _pb_field(8, b"deep"))  # an initializer [4] 'deep'
    for _ in range(33):
        graph = _pb_field(1, _pb_field(5, _pb_field(6, graph)))
    bundle = Bundle(lam_bundle)
    onnx_bytes = bundle.graph_bytes("deform") + _pb_field(7, graph)
    assert zlib.compress(onnx_bytes)
    assert [t.dims for t in model_tensors(onnx_bytes) if t.name == "deep"] == [[4]]


def test_onnxruntime_reason_is_one_line(lam_bundle, tmp_path):
    """A Constant node without an output (what a flipped bit made of a real one): onnxruntime's reason, which spans
    lines and quotes C++ signatures, reaches the BundleError on one line of at most MAX_REASON_CHARS."""
    import onnx

    from gaussiantalker.runtime.onnxruntime_backend import MAX_REASON_CHARS

    node = onnx.helper.make_node("Constant", [], [], value=onnx.helper.make_tensor("v", onnx.TensorProto.FLOAT,
                                                                                    [1], [0.0]))
    tail = _pb_field(7, _pb_field(1, node.SerializeToString()))
    text = _head_refusal(_head_bundle(lam_bundle, tmp_path / "constant.gtb", deform_tail=tail))
    reason = text.split("cannot be loaded by onnxruntime: ", 1)[1]
    assert len(reason) <= MAX_REASON_CHARS and "Constant" in reason, text


@pytest.mark.parametrize("background", [[1.0, 1.0], [1.0, 1.0, 1.0, 1.0], [1.0, [], 1.0], [1.0, "1", 1.0],
                                        [True, 1.0, 1.0], [1e39, 0.0, 0.0], [10**400, 0, 0], [[1.0, 1.0, 1.0]],
                                        {"r": 1}, "white", None],
                         ids=["2", "4", "list inside", "string inside", "bool inside", "1e39", "10^400", "nested",
                              "object", "string", "null"])
def test_manifest_background_must_be_three_finite_numbers(lam_bundle, tmp_path, background):
    """A manifest 'background' that is not 3 numbers finite in float32: BundleError naming the field."""
    path = _head_bundle(lam_bundle, tmp_path / "background.gtb", lambda manifest: manifest.update(
        background=background))
    assert "manifest 'background' must be 3 finite numbers" in _head_refusal(path)


@pytest.mark.parametrize("field, value, words", [
    ("R", [["x", 0, 0], [0, 1, 0], [0, 0, 1]], "R must be a (3, 3) array of real numbers"),
    ("R", [["x"] * 300] * 300, "entry [0, 0] is 'x'"),
    ("R", [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 10**400]], "entry [2, 2] is 1000"),
    ("t", [0.0, 0.0, 1e39], "t[2] = 1e+39"),
    ("R", [[2.0, 0, 0], [0, 2.0, 0], [0, 0, 2.0]], "det 8"),
    ("fx", "x" * 5000, "fx must be a real number, got 'xxx"),
], ids=["R of strings", "R 300x300 of strings", "R holding 10^400", "t = 1e39", "R scaled by 2", "fx 5,000 x's"])
def test_manifest_camera_refusals_are_short(lam_bundle, tmp_path, field, value, words):
    """A manifest camera holding strings, huge numbers or a scaled R: the refusal describes the shape and the first
    offending value on one short line, never a whole array's repr."""
    path = _head_bundle(lam_bundle, tmp_path / "camera.gtb", lambda manifest: manifest["camera"].update(
        {field: value}))
    text = _head_refusal(path)
    assert "manifest 'camera' section is invalid" in text and words in text, text


SCENE_HOLES = {
    "not UTF-8.toml": (b"[camera]\nwidth = 64\nheight = 64 # \xff\xfe\n", "is not UTF-8 text"),
    "nested arrays.json": (b'{"head": ' + b"[" * 100_000 + b"]" * 100_000 + b"}", "not valid JSON: it nests too deep"),
    "nested arrays.toml": (b"x = " + b"[" * 5000 + b"]" * 5000 + b"\n", "not valid TOML: it nests too deep"),
    "nested tables.toml": (b"x = " + b"{a = " * 3000 + b"1" + b"}" * 3000 + b"\n", "not valid TOML: it nests too"),
    "integer of 5,000 digits.json": (b'{"camera": {"width": ' + b"9" * 5000 + b', "height": 4}}', "(4300 digits)"),
    "integer of 5,000 digits.toml": (b"[camera]\nwidth = " + b"9" * 5000 + b"\nheight = 4\n", "(4300 digits)"),
    "range past float.json": (b'{"camera": {"width": 4, "height": 4}, "head": {"rotation_deg": [[1' + b"0" * 400 +
                              b", 2], [0, 0], [0, 0]]}}", "head.rotation_deg must be three"),
    "colour past float.json": (b'{"camera": {"width": 4, "height": 4}, "background": {"color": [1' + b"0" * 400 +
                               b", 0, 0]}}", "background.color must be three"),
    "camera a number.json": (b'{"camera": 5}', "[camera] must be a table"),
    "expression a number.toml": (b"[camera]\nwidth = 4\nheight = 4\n[drive]\nexpression = 3\n",
                                 "drive.expression must be"),
}


@pytest.mark.parametrize("name", list(SCENE_HOLES))
def test_scene_file_holes(tmp_path, name):
    """Each way a scene file escaped load_scene's SceneError (bad UTF-8, nesting, Python's integer digit limit,
    numbers past float's range, sections of the wrong type): one short line naming the file."""
    from gaussiantalker.sdk.scene import SceneError, load_scene

    data, words = SCENE_HOLES[name]
    path = tmp_path / name.replace(" ", "_").replace(",", "")
    path.write_bytes(data)
    with pytest.raises(SceneError) as refused:
        load_scene(path)
    text = str(refused.value)
    assert "\n" not in text and str(path) in text and words in text and len(text) < len(str(path)) + 300, text
