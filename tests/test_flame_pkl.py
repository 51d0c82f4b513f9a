"""FLAME's licensed pickle in, safely: `gt-import flame` on pickles written the way the real files are
(tests/flame_pickles.py), the npz it writes read back by load_flame_npz, and every bad or hostile file refused."""

from __future__ import annotations

import pickle
import pickletools
import subprocess
import sys

import numpy as np
import pytest
from flame_fuzz import Reduced, modern_dumps, subarray_attack_pickle
from flame_fuzz import dtype as forged_dtype
from flame_fuzz import frombuffer as forged_frombuffer
from flame_fuzz import reconstructed as forged_reconstructed
from flame_pickles import (
    UINT32_MAX,
    CscMatrix,
    FlameSpec,
    GlobalRef,
    chumpy_class,
    flame_model,
    py2_dumps,
    write_flame_pickle,
)
from typer.testing import CliRunner

from gaussiantalker.cli.imports import app
from gaussiantalker.exporter.imports.formats.flame_pkl import (
    FLAME_LAYOUT,
    MAX_PICKLE_BYTES,
    FlameLayout,
    convert_flame_pkl,
    detect_version,
    flame_arrays_from_pickle,
    load_flame_pickle,
    read_flame_npz_info,
)
from gaussiantalker.exporter.model.flame_npz import FLAME_NPZ_KEYS, load_flame_npz
from gaussiantalker.sdk.config import FLAME_PARENTS
from gaussiantalker.sdk.errors import ImportFormatError

SPEC = FlameSpec()
SMALL = FlameLayout(n_vertices=SPEC.n_vertices, n_faces=SPEC.n_faces)
# The globals a chumpy-era FLAME pickle references (protocol 2), as the writer puts them.
PY2_GLOBALS = {"chumpy.ch Ch", "__builtin__ set", "numpy.core.multiarray _reconstruct", "numpy ndarray",
               "numpy dtype", "scipy.sparse.csc csc_matrix"}


def _globals(data: bytes) -> set[str]:
    return {str(arg) for op, arg, _ in pickletools.genops(data) if op.name == "GLOBAL"}


def _assert_arrays_equal(arrays, npz_path, spec: FlameSpec) -> None:
    """The npz's FlameArrays hold exactly the arrays the pickle was made of (in float32)."""
    flame = load_flame_npz(npz_path, spec.n_shape, spec.n_expr)
    f32 = lambda a: np.asarray(a, dtype=np.float32)  # noqa: E731
    np.testing.assert_array_equal(flame.v_template, f32(arrays["v_template"]))
    np.testing.assert_array_equal(flame.shapedirs, f32(arrays["shapedirs"][:, :, : spec.n_shape]))
    np.testing.assert_array_equal(flame.exprdirs, f32(arrays["shapedirs"][:, :, spec.n_shape :]))
    np.testing.assert_array_equal(flame.posedirs, f32(arrays["posedirs"]).reshape(-1, 36).T)
    np.testing.assert_array_equal(flame.J_regressor, f32(arrays["J_regressor"]))
    np.testing.assert_array_equal(flame.lbs_weights, f32(arrays["weights"]))
    np.testing.assert_array_equal(flame.faces, arrays["f"].astype(np.int64))
    assert flame.parents == FLAME_PARENTS


@pytest.fixture(scope="module")
def full_pickle(tmp_path_factory):
    """A FLAME-sized pickle (5023 vertices, 300 + 100 columns), written as the real files are."""
    path = tmp_path_factory.mktemp("flame") / "generic_model.pkl"
    spec = FlameSpec(n_vertices=FLAME_LAYOUT.n_vertices, n_faces=FLAME_LAYOUT.n_faces)
    return path, spec, write_flame_pickle(path, spec)


def test_writer_references_what_a_real_file_does(tmp_path):
    """The synthetic pickles hold the real files' globals and Python-2 strings (the loader is tested on those)."""
    write_flame_pickle(tmp_path / "m.pkl", SPEC)
    raw = (tmp_path / "m.pkl").read_bytes()
    assert raw[:2] == b"\x80\x02" and _globals(raw) == PY2_GLOBALS
    ops = {op.name for op, _, _ in pickletools.genops(raw)}
    assert "NEWOBJ" in ops and not ops & {"BINUNICODE", "SHORT_BINUNICODE", "UNICODE"}  # Python-2 byte strings
    old = tmp_path / "old.pkl"
    write_flame_pickle(old, SPEC, protocol=1)
    assert _globals(old.read_bytes()) == PY2_GLOBALS | {"copy_reg _reconstructor", "__builtin__ object"}


@pytest.mark.parametrize("protocol", [2, 1])
def test_round_trip_small_layout(tmp_path, protocol):
    """pkl -> npz -> load_flame_npz gives the arrays put in, for both ways Python 2 pickled chumpy objects."""
    arrays = write_flame_pickle(tmp_path / "flame2023.pkl", SPEC, protocol=protocol)
    result = convert_flame_pkl(tmp_path / "flame2023.pkl", tmp_path / "flame.npz", layout=SMALL)
    assert (result.version, result.n_vertices, result.n_faces, result.n_shape, result.n_expr) == (
        "2023", SPEC.n_vertices, SPEC.n_faces, 300, 100)
    _assert_arrays_equal(arrays, tmp_path / "flame.npz", SPEC)
    assert read_flame_npz_info(tmp_path / "flame.npz") == {"flame_version": "2023", "n_shape": 300, "n_expr": 100}
    with np.load(tmp_path / "flame.npz", allow_pickle=False) as data:  # no pickles inside, the dtypes loaders expect
        assert {k: str(data[k].dtype) for k in FLAME_NPZ_KEYS} == {
            "v_template": "float32", "f": "int64", "shapedirs": "float32", "posedirs": "float32",
            "J_regressor": "float32", "weights": "float32", "kintree_table": "int64"}
        assert data["kintree_table"][0, 0] == UINT32_MAX
    assert sorted(p.name for p in tmp_path.iterdir()) == ["flame.npz", "flame2023.pkl"]  # no partial file left


def test_round_trip_full_size(full_pickle, tmp_path):
    path, spec, arrays = full_pickle
    result = convert_flame_pkl(path, tmp_path / "flame.npz")
    assert (result.version, result.n_vertices, result.n_expr) == ("2020", 5023, 100)
    _assert_arrays_equal(arrays, tmp_path / "flame.npz", spec)


@pytest.mark.parametrize(("protocol", "numpy_global"), [(5, "numpy._core.numeric _frombuffer"),
                                                        (2, "numpy._core.multiarray _reconstruct")])
def test_modern_pickle_and_chumpy_expressions(tmp_path, protocol, numpy_global):
    """A pickle of Python 3 and newer numpy/scipy (protocol 5: _frombuffer; protocol 2: bytes by _codecs.encode;
    scipy.sparse._csc) holding chumpy Select/transpose expressions."""
    arrays = flame_model(SPEC)

    class Csc:  # scipy.sparse._csc.csc_matrix, as newer scipy names it
        def __init__(self, dense):
            cols = [np.nonzero(dense[:, j])[0] for j in range(dense.shape[1])]
            self.__dict__.update(_shape=dense.shape, indices=np.concatenate(cols),
                                 indptr=np.cumsum([0] + [len(c) for c in cols]),
                                 data=np.concatenate([dense[c, j] for j, c in enumerate(cols)]))
    Csc.__module__, Csc.__qualname__ = "scipy.sparse._csc", "csc_matrix"
    select, transpose, ch = (chumpy_class(p) for p in ("chumpy.reordering.Select", "chumpy.reordering.transpose",
                                                        "chumpy.ch.Ch"))
    flat = arrays["shapedirs"].ravel()
    model = {**arrays, "J_regressor": Csc(arrays["J_regressor"]),
             "shapedirs": select({"a": ch({"x": flat[::-1].copy()}), "idxs": np.arange(flat.size)[::-1].copy(),
                                  "preferred_shape": arrays["shapedirs"].shape}),
             "weights": transpose({"a": ch({"x": arrays["weights"].T.copy()}), "axes": None})}
    fake = {name: type(sys)(name) for name in ("chumpy", "chumpy.ch", "chumpy.reordering", "scipy.sparse._csc")}
    fake["chumpy.ch"].Ch, fake["chumpy.reordering"].Select = ch, select
    fake["chumpy.reordering"].transpose, fake["scipy.sparse._csc"].csc_matrix = transpose, Csc
    # pickle imports a class's module with its parents: stand-ins for those too where SciPy is not imported (or not
    # installed: the SDK never needs it)
    fake.update({name: type(sys)(name) for name in ("scipy", "scipy.sparse") if name not in sys.modules})
    saved = {name: sys.modules.get(name) for name in fake}
    sys.modules.update(fake)
    try:
        data = pickle.dumps(model, protocol=protocol)
    finally:
        for name, module in saved.items():
            if module is None:
                sys.modules.pop(name)
            else:
                sys.modules[name] = module
    found = _globals(data) | {" ".join(pair) for pair in _stack_globals(data)}
    assert {numpy_global, "scipy.sparse._csc csc_matrix"} <= found
    assert ("_codecs encode" in found) == (protocol == 2)
    (tmp_path / "flame2023_Open.pkl").write_bytes(data)
    result = convert_flame_pkl(tmp_path / "flame2023_Open.pkl", tmp_path / "out.npz", layout=SMALL)
    assert result.version == "2023 Open"
    _assert_arrays_equal(arrays, tmp_path / "out.npz", SPEC)


def _stack_globals(data: bytes) -> set[tuple[str, str]]:
    """(module, name) of each STACK_GLOBAL (protocol 4+): the two strings pushed before it."""
    found, recent = set(), []
    for op, arg, _ in pickletools.genops(data):
        if op.name in ("SHORT_BINUNICODE", "BINUNICODE"):
            recent = [*recent[-1:], arg]
        elif op.name == "MEMOIZE":
            continue
        elif op.name == "STACK_GLOBAL":
            found.add(tuple(recent))
        else:
            recent = []
    return found


def _marker_payload(marker, via: str) -> bytes:
    """A pickle that creates `marker` when loaded by a plain unpickler."""
    if via == "os.system":
        return f"cos\nsystem\n(S'touch {marker}'\ntR.".encode()
    code = f"open({str(marker)!r}, 'w').close()"
    return f"c__builtin__\neval\n(S{code!r}\ntR.".encode()


@pytest.mark.parametrize("via", ["os.system", "builtins.eval"])
def test_evil_pickle_refused_without_running(tmp_path, via):
    marker = tmp_path / "pwned"
    payload = _marker_payload(marker, via)
    pickle.loads(payload)  # the payload works: a plain unpickler runs it ...
    assert marker.exists()
    marker.unlink()
    (tmp_path / "evil.pkl").write_bytes(payload)
    name = "os.system" if via == "os.system" else "__builtin__.eval"
    with pytest.raises(ImportFormatError, match=f"references {name}, which no FLAME model holds"):
        load_flame_pickle(tmp_path / "evil.pkl")
    assert not marker.exists()  # ... the importer does not


def test_evil_payload_inside_a_flame_model(tmp_path):
    """A `__reduce__` payload hidden in an otherwise valid FLAME dict: refused, nothing runs, no npz written."""
    marker = tmp_path / "pwned"

    class Payload:
        def __reduce__(self):
            return eval, (f"open({str(marker)!r}, 'w').close()",)

    write_flame_pickle(tmp_path / "m.pkl", SPEC, edit=lambda model: model.update(bs_style=Payload()))
    with pytest.raises(ImportFormatError, match=r"__builtin__\.eval.*nothing from the file ran"):
        convert_flame_pkl(tmp_path / "m.pkl", tmp_path / "out.npz", layout=SMALL)
    assert not marker.exists() and not (tmp_path / "out.npz").exists()
    pickle.loads(py2_dumps(Payload()))  # the payload alone, loaded by a plain unpickler, runs
    assert marker.exists()


def test_object_arrays_and_stand_in_misuse_refused(tmp_path):
    (tmp_path / "obj.pkl").write_bytes(py2_dumps({"v_template": np.array([{"a": 1}], dtype=object)}))
    with pytest.raises(ImportFormatError, match="holds Python objects"):
        load_flame_pickle(tmp_path / "obj.pkl")
    # numpy.ndarray is only an argument to _reconstruct: calling it is refused
    (tmp_path / "nd.pkl").write_bytes(b"cnumpy\nndarray\n(I100000000000\ntR.")
    with pytest.raises(ImportFormatError, match="not a readable pickle"):
        load_flame_pickle(tmp_path / "nd.pkl")


@pytest.mark.parametrize("target", ["numpy\ndtype", "numpy\nndarray", "chumpy.ch\nCh"])
def test_stand_ins_cannot_be_altered(tmp_path, target):
    """A BUILD on a reconstructor or stand-in class (to change it for later loads) fails, and later loads work."""
    (tmp_path / "alter.pkl").write_bytes(f"c{target}\n(N}}(S'function'\nc__builtin__\nset\nutb.".encode())
    with pytest.raises(ImportFormatError, match="set 'function' on a reconstructor|__setstate__"):
        load_flame_pickle(tmp_path / "alter.pkl")
    arrays = write_flame_pickle(tmp_path / "m.pkl", SPEC)
    np.testing.assert_array_equal(flame_arrays_from_pickle(tmp_path / "m.pkl", SMALL)["v_template"],
                                  arrays["v_template"].astype(np.float32))


def test_truncated_and_non_pickle_files(tmp_path):
    write_flame_pickle(tmp_path / "m.pkl", SPEC)
    raw = (tmp_path / "m.pkl").read_bytes()
    (tmp_path / "cut.pkl").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ImportFormatError, match=r"cut\.pkl: not a readable pickle \(truncated or damaged\?\)"):
        load_flame_pickle(tmp_path / "cut.pkl")
    (tmp_path / "text.pkl").write_text("v 0 0 0\nf 1 2 3\n")
    with pytest.raises(ImportFormatError, match=r"text\.pkl: not a readable pickle"):
        load_flame_pickle(tmp_path / "text.pkl")
    np.savez(tmp_path / "model.npz", v_template=np.zeros((3, 3)))
    with pytest.raises(ImportFormatError, match="zip/npz archive, not a pickle"):
        load_flame_pickle(tmp_path / "model.npz")
    (tmp_path / "list.pkl").write_bytes(pickle.dumps([1, 2], protocol=2))
    with pytest.raises(ImportFormatError, match="holds a list, expected FLAME's dict"):
        load_flame_pickle(tmp_path / "list.pkl")
    with pytest.raises(ImportFormatError, match="cannot read"):
        load_flame_pickle(tmp_path / "absent.pkl")


def _drop(key):
    return lambda model: model.pop(key)


@pytest.mark.parametrize(("spec", "edit", "message"), [
    (FlameSpec(n_expr=50), None, r"'shapedirs' has shape \[40, 3, 350\], expected \[40, 3, 400\] "
                                 r"\(300 shape \+ 50 expression columns; FLAME 2020 and FLAME 2023 have 300 \+ 100\)"),
    (FlameSpec(n_shape=300, n_expr=0), None, r"'shapedirs' has shape \[40, 3, 300\].*identity shape only"),
    (SPEC, _drop("weights"), r"not a FLAME model: missing 'weights' \(it holds 'J', 'J_regressor'"),
    (FlameSpec(n_faces=59), None, r"'f' has shape \[59, 3\], expected \[60, 3\]"),
    (SPEC, lambda m: m.update(f=np.zeros((60, 4), dtype=np.uint32)), r"'f' has shape \[60, 4\], expected \[60, 3\]"),
    (SPEC, lambda m: m.update(f=np.zeros((60, 3))), r"'f' has dtype float64, expected integers"),
    (SPEC, lambda m: m.update(posedirs=m["J"]), r"'posedirs' has shape \[5, 3\], expected \[40, 3, 36\]"),
    (SPEC, lambda m: m.update(weights=[[1.0]]), r"'weights' is a list, not an array"),
    (SPEC, lambda m: m.update(weights=chumpy_class("chumpy.ch_ops.add")({"a": 1, "b": 2})),
     r"'weights' is a chumpy expression \(chumpy\.ch_ops\.add\), not a stored array"),
])
def test_wrong_layouts_name_the_field(tmp_path, spec, edit, message):
    write_flame_pickle(tmp_path / "m.pkl", spec, edit=edit)
    with pytest.raises(ImportFormatError, match=message):
        flame_arrays_from_pickle(tmp_path / "m.pkl", SMALL)


def test_other_models_are_named(tmp_path):
    """A body model's pickle (SMPL's 6890 vertices) against FLAME's full layout: one error saying what it is."""
    write_flame_pickle(tmp_path / "smpl.pkl", FlameSpec(n_vertices=6890, n_faces=10, n_shape=10, n_expr=0))
    with pytest.raises(ImportFormatError, match=r"'v_template' has shape \[6890, 3\], expected \[5023, 3\] "
                                                r"\(6890 vertices: SMPL / SMPL\+H \(a body model\), not FLAME\)"):
        flame_arrays_from_pickle(tmp_path / "smpl.pkl")


def test_bad_content_with_flame_shapes(tmp_path):
    """FLAME's shapes but not its content (skinning weights that do not sum to 1): load_flame_npz's check, no npz."""
    write_flame_pickle(tmp_path / "m.pkl", SPEC, edit=lambda m: m["weights"].__dict__.update(x=np.ones((40, 5))))
    with pytest.raises(ImportFormatError, match="'lbs_weights' rows must sum to 1"):
        convert_flame_pkl(tmp_path / "m.pkl", tmp_path / "out.npz", layout=SMALL)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.pkl"]


def test_numpy_scalars_and_csr(tmp_path):
    """A sparse shape held as numpy integers (numpy.core.multiarray.scalar) and a CSR J_regressor read the same."""
    class CsrMatrix(CscMatrix):  # the CSC of the transpose is the CSR of the matrix
        pass
    CsrMatrix.__module__, CsrMatrix.__qualname__ = "scipy.sparse.csr", "csr_matrix"

    def numpy_shape(model):
        model["J_regressor"]._shape = tuple(np.int64(n) for n in model["J_regressor"]._shape)

    dense = flame_model(SPEC)["J_regressor"]

    def csr(model):
        model["J_regressor"] = CsrMatrix(dense.T)
        model["J_regressor"]._shape = dense.shape

    for name, edit, global_name in (("scalar.pkl", numpy_shape, "numpy.core.multiarray scalar"),
                                    ("csr.pkl", csr, "scipy.sparse.csr csr_matrix")):
        arrays = write_flame_pickle(tmp_path / name, SPEC, edit=edit)
        assert global_name in _globals((tmp_path / name).read_bytes())
        np.testing.assert_array_equal(flame_arrays_from_pickle(tmp_path / name, SMALL)["J_regressor"],
                                      arrays["J_regressor"].astype(np.float32))


def test_sparse_regressor_checked(tmp_path):
    def corrupt(model):
        model["J_regressor"].indices = model["J_regressor"].indices + 1000
    write_flame_pickle(tmp_path / "m.pkl", SPEC, edit=corrupt)
    with pytest.raises(ImportFormatError, match=r"'J_regressor' \(scipy\.sparse\.csc\.csc_matrix\) has inconsistent"):
        flame_arrays_from_pickle(tmp_path / "m.pkl", SMALL)


@pytest.mark.parametrize(("name", "version"), [
    ("generic_model.pkl", "2020"), ("flame2023.pkl", "2023"), ("flame2023_no_jaw.pkl", "2023 (no jaw rotation)"),
    ("FLAME2020/female_model.pkl", "2020"), ("head.pkl", "unknown"),
])
def test_detect_version(name, version):
    assert detect_version(name) == version


def test_cli(full_pickle, tmp_path):
    path, spec, arrays = full_pickle
    out = tmp_path / "flame.npz"
    result = CliRunner().invoke(app, ["flame", str(path), "-o", str(out)])
    assert result.exit_code == 0, result.output
    assert "FLAME 2020: 5023 vertices, 9976 faces, 300 shape + 100 expression columns" in result.output
    assert str(out) in result.output
    _assert_arrays_equal(arrays, out, spec)
    result = CliRunner().invoke(app, ["flame", str(path), "-o", str(out), "--flame-version", "2023"])
    assert result.exit_code == 0 and read_flame_npz_info(out)["flame_version"] == "2023"
    (tmp_path / "bad.pkl").write_bytes(b"cos\nsystem\n(S'true'\ntR.")
    result = CliRunner().invoke(app, ["flame", str(tmp_path / "bad.pkl")])
    assert result.exit_code == 2
    assert result.output.strip().splitlines() == [
        f"error: {tmp_path / 'bad.pkl'}: not a FLAME model pickle: it references os.system, which no FLAME model "
        "holds: refused, nothing from the file ran"]
    assert not (tmp_path / "bad.npz").exists()


# ------------------------------------------------------------------------------------------------ forged numpy state
# The subarray attack and its family (tests/flame_fuzz.py builds them): a dtype, array or number whose pickled
# state describes more memory than the file gives it. A plain unpickler trusts that state; the reader must not.


def test_subarray_attack_pickle_reads_memory_when_trusted(tmp_path):
    """The subarray attack is real: a plain unpickler (in a child process, as it may crash) returns an array of
    8000 bytes from an 8-byte buffer, i.e. the process's own memory."""
    script = ("import sys, pickle; sys.path.insert(0, 'tests'); from flame_fuzz import subarray_attack_pickle; "
              "a = pickle.loads(subarray_attack_pickle(1000)); print(a.nbytes, a.base is not None)")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["8000", "True"]


@pytest.mark.parametrize("n_sub", [2, 1000, 100_000_000])
def test_subarray_attack_pickle_refused_by_the_cli(tmp_path, n_sub):
    """`gt-import flame` on the subarray attack (100,000,000 elements: a size that crashes a trusting reader): one
    line naming the file, exit 2, no npz."""
    path = tmp_path / "generic_model.pkl"
    path.write_bytes(subarray_attack_pickle(n_sub))
    assert b"_codecs" in path.read_bytes() and b"_frombuffer" in path.read_bytes()
    result = CliRunner().invoke(app, ["flame", str(path), "-o", str(tmp_path / "out.npz")])
    assert result.exit_code == 2, result.output
    assert result.output.strip().splitlines() == [
        f"error: {path}: not a FLAME model pickle: numpy dtype with a subarray or fields (no FLAME array has one)"]
    assert not (tmp_path / "out.npz").exists()


F8_STATE = (3, "<", None, None, None, -1, -1, 0)


@pytest.mark.parametrize(("value", "message"), [
    (forged_dtype("f8", (3, "|", (forged_dtype("f8"), (4,)), None, None, 32, 1, 0)), "subarray or fields"),
    (forged_dtype("V16", (3, "|", None, ("a",), {"a": (forged_dtype("f8"), 0)}, 16, 1, 0)),
     r"numpy\.dtype of 'V16'"),
    (forged_dtype("f8", (3, "|", None, ("a",), {"a": (forged_dtype("f8"), 0)}, 8, 1, 0)), "subarray or fields"),
    (forged_dtype("(1000,)f8"), r"numpy\.dtype of '\(1000,\)f8', which is not a plain"),
    (forged_dtype("f8,i4"), r"numpy\.dtype of 'f8,i4'"),
    (forged_dtype("f8", (3, "<", None, None, None, 4096, -1, 0)), "float64 with an item size of 4096 bytes"),
    (forged_dtype("f8", (3, "?", None, None, None, -1, -1, 0)), r"byte order '\?'"),
    (forged_dtype("f8", (3, "<")), "not a dtype's 8- or 9-tuple"),
    (forged_dtype("S", (3, "|", None, None, None, -8, 1, 0)), "S dtype of -8 bytes"),
    (forged_dtype("U", (3, "<", None, None, None, 6, 4, 8)), "U dtype of 6 bytes"),
    (forged_reconstructed((1, (1000,), forged_dtype("f8"), False, b"\0" * 8)),
     r"8 bytes for a \[1000\] array of float64 \(8000 bytes\)"),
    (forged_reconstructed((1, (2**62, 2**62), forged_dtype("f8"), False, b"")), r"0 bytes for a \[4611686018427387904"),
    (forged_reconstructed((1, (-1,), forged_dtype("f8"), False, b"")), r"with shape \(-1,\)"),
    (forged_reconstructed((1, (1,), forged_dtype("f8"), False, [1.0])), "of a list, expected bytes"),
    (forged_reconstructed((1, (1,), "f8", False, b"\0" * 8)), r"without a plain numpy dtype \(a str\)"),
    (forged_frombuffer(b"\0" * 8, forged_dtype("f8"), (4, 4)), r"8 bytes for a \[4, 4\] array"),
    (forged_frombuffer(b"\0" * 8, forged_dtype("f8"), (1,), "K"), "in order 'K'"),
    (Reduced(GlobalRef("numpy.core.multiarray", "scalar"), (forged_dtype("f8"), b"\0" * 4)), r"4 bytes for a \[\]"),
    (Reduced(GlobalRef("numpy", "dtype"), ("f8", 0, 1), F8_STATE, None, None),  # dtype built twice, by BUILD
     None),
])
def test_forged_numpy_state_refused(tmp_path, value, message):
    """Each forged dtype, array or number (inside an otherwise valid model) is refused before any array is made
    from it, with what is wrong; a plain dtype built once is accepted (message None)."""
    write_flame_pickle(tmp_path / "m.pkl", SPEC, edit=lambda model: model.update(bs_style=value))
    if message is None:
        assert isinstance(load_flame_pickle(tmp_path / "m.pkl")["bs_style"], np.dtype)
        return
    with pytest.raises(ImportFormatError, match=message):
        load_flame_pickle(tmp_path / "m.pkl")


def test_build_on_reconstructed_values_refused(tmp_path):
    """A second BUILD on a dtype or an array, or any BUILD on a `_frombuffer` result, is refused (only the inert
    stand-ins take a state, once)."""
    good = py2_dumps({"a": forged_frombuffer(b"\0" * 8, forged_dtype("f8"), (1,))})
    assert load_flame_pickle(_write(tmp_path / "good.pkl", good))["a"].tolist() == [0.0]
    cases = {
        "frombuffer.pkl": (good[:-2] + b"}b" + good[-2:], "set up a value with a __setstate__ state"),
        "dtype.pkl": (b"\x80\x02cnumpy\ndtype\nU\x02f8K\x00K\x01\x87R(K\x03U\x01<NNNJ\xff\xff\xff\xffJ\xff\xff\xff"
                      b"\xffK\x00tb(K\x03U\x01>NNNJ\xff\xff\xff\xffJ\xff\xff\xff\xffK\x00tb.",
                      "a numpy dtype is set up twice"),
    }
    for name, (data, message) in cases.items():
        with pytest.raises(ImportFormatError, match=message):
            load_flame_pickle(_write(tmp_path / name, data))


def _write(path, data: bytes):
    path.write_bytes(data)
    return path


@pytest.mark.parametrize("dtype", [">f8", "<f4", ">i4", "|u1", "|b1", "<c8", "|S7", ">U3", "<U2"])
def test_plain_dtypes_round_trip(tmp_path, dtype):
    """Every plain dtype a FLAME file may hold (either byte order, text and bytes) reads back equal, as a
    native-memory array that owns its bytes."""
    values = np.arange(6).reshape(2, 3).astype(dtype)
    for protocol in (1, 2):
        path = _write(tmp_path / f"p{protocol}.pkl", py2_dumps({"a": values}, protocol))
        read = load_flame_pickle(path)["a"]
        np.testing.assert_array_equal(read, values)
        assert read.dtype == values.dtype and read.flags.owndata
    read = load_flame_pickle(_write(tmp_path / "p5.pkl", modern_dumps({"a": values})))["a"]
    np.testing.assert_array_equal(read, values)


def test_lying_lengths_are_bounded_by_the_file(tmp_path):
    """An opcode stating more bytes than the file holds is refused before the unpickler allocates for it, and a
    file larger than any FLAME model is refused before it is read."""
    lying = b"\x80\x05\x8e" + (2**56).to_bytes(8, "little") + b"\0" * 8 + b"."  # BINBYTES8 of 2**56 bytes
    with pytest.raises(ImportFormatError, match=r"not a readable pickle .*expected 72057594037927936 bytes"):
        load_flame_pickle(_write(tmp_path / "lying.pkl", lying))
    huge = tmp_path / "huge.pkl"
    with huge.open("wb") as handle:
        handle.truncate(MAX_PICKLE_BYTES + 1)  # sparse: no disk used
    with pytest.raises(ImportFormatError, match=r"huge\.pkl: 1073741825 bytes, more than any FLAME model pickle"):
        load_flame_pickle(huge)
