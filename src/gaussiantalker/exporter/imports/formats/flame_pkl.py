"""FLAME's licensed pickle (generic_model.pkl, flame2023.pkl) read without running it, and written as the SDK's
FLAME npz (docs/import.md, "FLAME model files").

The file is a Python-2 pickle of chumpy `Ch` objects, a scipy sparse `J_regressor` and numpy arrays. A restricted
unpickler maps each global such a file references to a stand-in that only builds plain data: chumpy objects and
sparse matrices keep their pickled state (a dict of arrays), numpy's array and dtype reconstructors build arrays
from the file's bytes. Every other global is refused by name before anything is called; neither chumpy nor scipy
is ever imported.
"""

from __future__ import annotations

import io
import math
import pickle
import pickletools
import re
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gaussiantalker.sdk.codecs import MAX_NDIM
from gaussiantalker.sdk.errors import CheckpointError, ImportFormatError
from gaussiantalker.sdk.files import atomic_path
from gaussiantalker.sdk.zip_reader import read_npz

from ...model.flame import N_JOINTS, POSE_FEATURE_DIM
from ...model.flame_npz import FLAME_NPZ_KEYS, FLAME_SHAPE_COLUMNS, load_flame_npz

# chumpy's modules whose classes a model file may hold; any class there becomes an inert state holder.
CHUMPY_MODULES = ("chumpy.ch", "chumpy.ch_ops", "chumpy.reordering", "chumpy.linalg", "chumpy.logic")
# scipy's sparse classes by module path: Python-2-era files (scipy.sparse.csc) and newer scipy (scipy.sparse._csc).
SPARSE_CLASSES = {
    f"scipy.sparse.{module}.{kind}_{suffix}": kind
    for kind in ("csc", "csr")
    for module in (kind, f"_{kind}")
    for suffix in ("matrix", "array")
}
# Extra npz entries recording where the arrays came from (load_flame_npz reads only FLAME_NPZ_KEYS).
VERSION_KEY = "flame_version"
N_SHAPE_KEY = "n_shape"
N_EXPR_KEY = "n_expr"
# The largest pickle read (FLAME 2020 and 2023 are about 100 MB): the file is read whole, then checked.
MAX_PICKLE_BYTES = 1 << 30
# A chumpy expression deeper than this is not a stored array (and could be a reference loop).
_MAX_DEPTH = 8
_IDENTIFIER = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")
# Vertex counts of the other chumpy-pickled models of the same family, to say what a wrong file is.
_OTHER_MODELS = {6890: "SMPL / SMPL+H (a body model)", 10475: "SMPL-X (a body model)", 778: "MANO (a hand model)"}


@dataclass(frozen=True)
class FlameLayout:
    """The array shapes a FLAME model file must have (FLAME 2020 and FLAME 2023 share them)."""

    n_vertices: int = 5023
    n_faces: int = 9976
    n_shape: int = FLAME_SHAPE_COLUMNS
    n_expr: int = 100

    def expected(self) -> dict[str, tuple[int, ...]]:
        """Shape of each FLAME_NPZ_KEYS entry."""
        v = self.n_vertices
        return {
            "v_template": (v, 3),
            "f": (self.n_faces, 3),
            "shapedirs": (v, 3, self.n_shape + self.n_expr),
            "posedirs": (v, 3, POSE_FEATURE_DIM),
            "J_regressor": (N_JOINTS, v),
            "weights": (v, N_JOINTS),
            "kintree_table": (2, N_JOINTS),
        }


FLAME_LAYOUT = FlameLayout()


@dataclass(frozen=True)
class FlameImport:
    """What `convert_flame_pkl` wrote."""

    output: Path
    version: str
    n_vertices: int
    n_faces: int
    n_shape: int
    n_expr: int
    seconds: float


# ------------------------------------------------------------------------------------------------ stand-ins


class PickleRefused(pickle.UnpicklingError):
    """The file references a global, or hands a reconstructor an argument, that no FLAME model does (nothing of
    the file's was called)."""


class _StandIn:
    """An object the file pickled (a chumpy node, a sparse matrix): its class path and pickled state, inert."""

    path = ""
    state: dict

    def __setstate__(self, state: object) -> None:
        if not isinstance(state, dict):
            raise PickleRefused(f"{self.path} holds a {type(state).__name__} state, expected a dict")
        self.state = state


class _ChumpyNode(_StandIn):
    """A chumpy `Ch` (or a chumpy expression): its array lives in its state."""


class _SparseMatrix(_StandIn):
    """A scipy CSC/CSR matrix: data, indices, indptr and shape in its state."""

    kind = "csc"


class _Frozen:
    """No `__dict__`, no `__setstate__`, no attribute setting: a pickle's BUILD cannot alter it for later loads."""

    __slots__ = ()

    def __setattr__(self, name: str, value: object) -> None:
        raise PickleRefused(f"the file tries to set {name!r} on a reconstructor; refused")

    def __setstate__(self, state: object) -> None:
        raise PickleRefused(f"the file tries to set up a {type(self).__name__.strip('_').lower()} with a "
                            "__setstate__ state; refused")


class _Marker(_Frozen):
    """A global only ever passed as an argument (numpy.ndarray to `_reconstruct`); neither callable nor a type."""

    __slots__ = ("path",)

    def __init__(self, path: str) -> None:
        object.__setattr__(self, "path", path)


class _Call(_Frozen):
    """One of the functions below as the unpickler sees it: callable, unalterable."""

    __slots__ = ("function",)

    def __init__(self, function: Callable[..., object]) -> None:
        object.__setattr__(self, "function", function)

    def __call__(self, *args: object) -> object:
        return self.function(*args)


_NDARRAY = _Marker("numpy.ndarray")
_STAND_IN_TYPES: dict[str, type[_StandIn]] = {}


def _stand_in(base: type[_StandIn], path: str, **attrs: object) -> type[_StandIn]:
    """One stand-in class per pickled class path (the unpickler instantiates classes, so each needs its own)."""
    if path not in _STAND_IN_TYPES:
        _STAND_IN_TYPES[path] = type(base.__name__, (base,), {"path": path, **attrs})
    return _STAND_IN_TYPES[path]


# numpy type strings a FLAME file's arrays use: booleans, integers, floats, complex, bytes and text, with an
# optional byte order and size. Anything else (structured "f8,i4", subarray "(3,)f8", objects, datetimes, void) is
# refused before numpy parses it.
_TYPE_STRING = re.compile(r"[<>|=]?(?:b1|\?|[iu][1248]|f[248]|c(?:8|16)|[SU][0-9]{0,9})\Z")
# A pickled dtype's state: (version, byte order, subarray, names, fields, elsize, alignment, flags[, metadata]).
_DTYPE_STATE_LENGTHS = (8, 9)


def _canonical_type(spec: object) -> np.dtype:
    """A plain dtype parsed from a checked type string; bytes and text without a size stay unsized ("S", "U")."""
    if isinstance(spec, bytes):
        spec = spec.decode("latin1")
    if isinstance(spec, str) and spec.lstrip("<>|=").startswith("O"):
        raise PickleRefused(f"numpy dtype {spec} holds Python objects; refused")
    if not isinstance(spec, str) or not _TYPE_STRING.match(spec):
        raise PickleRefused(f"numpy.dtype of {spec!r}, which is not a plain number, byte or text type")
    return np.dtype(spec)


class _PickledDtype:
    """`numpy.dtype(spec)` as a pickle builds it: the checked type string, and the byte order or size its BUILD
    state gives. The dtype handed on is always made afresh from these (`canonical`), never from the state itself:
    numpy trusts a dtype state's sizes, so a forged one describes more memory than its arrays own."""

    def __init__(self, spec: object) -> None:
        self.base = _canonical_type(spec)
        self.byte_order = "="
        self.size = self.base.itemsize
        self.built = False

    def __setstate__(self, state: object) -> None:
        if self.built:
            raise PickleRefused("a numpy dtype is set up twice")
        self.built = True
        if not isinstance(state, tuple) or len(state) not in _DTYPE_STATE_LENGTHS:
            raise PickleRefused(f"numpy dtype state {type(state).__name__} is not a dtype's 8- or 9-tuple")
        _version, byte_order, subarray, names, fields, elsize, _alignment, _flags = state[:8]
        if subarray is not None or names is not None or fields is not None:
            raise PickleRefused("numpy dtype with a subarray or fields (no FLAME array has one)")
        if byte_order not in ("<", ">", "|", "="):
            raise PickleRefused(f"numpy dtype byte order {byte_order!r}")
        if not isinstance(elsize, int) or isinstance(elsize, bool):
            raise PickleRefused(f"numpy dtype item size {elsize!r}")
        self.byte_order = byte_order
        if self.base.kind in "SU" and elsize != -1:
            self.size = elsize
        elif elsize not in (-1, self.base.itemsize):
            raise PickleRefused(f"numpy dtype {self.base} with an item size of {elsize} bytes")

    def canonical(self) -> np.dtype:
        """The plain dtype this stands for, built from its type string, byte order and size alone."""
        dtype = self.base
        if dtype.kind in "SU":
            unit = 4 if dtype.kind == "U" else 1
            if self.size <= 0 or self.size % unit or self.size > 1 << 30:
                raise PickleRefused(f"numpy {dtype.kind} dtype of {self.size} bytes")
            dtype = np.dtype(f"{dtype.kind}{self.size // unit}")
        if dtype.itemsize > 1 and self.byte_order in "<>":
            dtype = dtype.newbyteorder(self.byte_order)
        return dtype


def _dtype(spec: object, align: object = False, copy: object = True) -> _PickledDtype:
    """numpy.dtype as pickles call it: a stand-in for a plain dtype, which its BUILD may only give a byte order."""
    return _PickledDtype(spec)


def _plain_dtype(dtype: object, what: str) -> np.dtype:
    """The canonical dtype of a reconstructor's dtype argument (only ever a `_PickledDtype`)."""
    if not isinstance(dtype, _PickledDtype):
        raise PickleRefused(f"{what} without a plain numpy dtype (a {type(dtype).__name__})")
    return dtype.canonical()


def _shape(shape: object, what: str) -> tuple[int, ...]:
    """An array shape from the file: a tuple of non-negative Python ints."""
    if isinstance(shape, int) and not isinstance(shape, bool):
        shape = (shape,)
    if (not isinstance(shape, tuple) or len(shape) > MAX_NDIM
            or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape)):
        raise PickleRefused(f"{what} with shape {shape!r}")
    return shape


def _array_from_bytes(raw: object, dtype: np.dtype, shape: tuple[int, ...], fortran: bool, what: str) -> np.ndarray:
    """A copy of `raw` as an array, after checking that its bytes are exactly what the shape and dtype need."""
    if isinstance(raw, str):  # Python 2's str arrives as latin-1 text
        raw = raw.encode("latin1")
    if isinstance(raw, pickle.PickleBuffer):
        raw = raw.raw()
    if not isinstance(raw, bytes | bytearray | memoryview):
        raise PickleRefused(f"{what} of a {type(raw).__name__}, expected bytes")
    needed = math.prod(shape) * dtype.itemsize  # Python ints: no overflow
    if len(raw) != needed:
        raise PickleRefused(f"{what}: {len(raw)} bytes for a {list(shape)} array of {dtype} ({needed} bytes)")
    return np.frombuffer(raw, dtype=dtype).reshape(shape, order="F" if fortran else "C").copy()


class _Value(_Frozen):
    """An array or numpy number a reconstructor made: inert (a BUILD on it is refused), unwrapped after loading."""

    __slots__ = ("value",)

    def __init__(self, value: object) -> None:
        object.__setattr__(self, "value", value)


class _PickledArray:
    """numpy's `_reconstruct` result, which the pickle's BUILD fills: its state is checked against its bytes."""

    def __init__(self) -> None:
        self.value: np.ndarray | None = None

    def __setstate__(self, state: object) -> None:
        if self.value is not None:
            raise PickleRefused("a numpy array is filled twice")
        if isinstance(state, tuple) and len(state) == 5:
            version, *state = state
            if version != 1:
                raise PickleRefused(f"numpy array state version {version!r}")
        if not isinstance(state, tuple | list) or len(state) != 4:
            raise PickleRefused(f"numpy array state {type(state).__name__} is not an array's 4- or 5-tuple")
        shape, dtype, fortran, raw = state
        what = "a numpy array"
        self.value = _array_from_bytes(raw, _plain_dtype(dtype, what), _shape(shape, what), bool(fortran), what)


def _reconstruct(subtype: object, shape: object, dtype: object) -> _PickledArray:
    """numpy's `_reconstruct`: an array stand-in that the pickle's BUILD fills from the file's bytes."""
    if subtype is not _NDARRAY:
        raise PickleRefused("numpy _reconstruct of something other than numpy.ndarray")
    return _PickledArray()


def _frombuffer(buffer: object, dtype: object, shape: object, order: object) -> _Value:
    """numpy's `_frombuffer` (protocol-5 pickles of newer numpy): a copy of the bytes as an array."""
    what = "numpy _frombuffer"
    if order not in ("C", "F"):
        raise PickleRefused(f"{what} in order {order!r}")
    return _Value(_array_from_bytes(buffer, _plain_dtype(dtype, what), _shape(shape, what), order == "F", what))


def _scalar(dtype: object, data: object = b"") -> _Value:
    """numpy's `scalar` (a pickled numpy number, e.g. a sparse shape held as numpy integers), plain dtypes only."""
    return _Value(_array_from_bytes(data, _plain_dtype(dtype, "numpy scalar"), (), False, "numpy scalar")[()])


def _reconstructor(cls: object, base: object, state: object) -> _StandIn:
    """copyreg's `_reconstructor` (protocol 0/1 pickles of new-style classes), for stand-ins only."""
    if not (isinstance(cls, type) and issubclass(cls, _StandIn)) or base is not object or state is not None:
        raise PickleRefused("copy_reg._reconstructor of something other than a chumpy or sparse object")
    return cls.__new__(cls)


def _encode(text: object, encoding: object = "latin1") -> bytes:
    """`_codecs.encode` as Python 3 pickles bytes at protocol 2 (a re-saved model): latin-1 text to bytes only."""
    if not isinstance(text, str) or encoding not in ("latin1", "latin-1"):
        raise PickleRefused(f"_codecs.encode of a {type(text).__name__} as {encoding!r}")
    return text.encode("latin1")


_GLOBALS: dict[str, object] = {
    **{f"numpy.{core}.multiarray._reconstruct": _Call(_reconstruct) for core in ("core", "_core")},
    **{f"numpy.{core}.multiarray.scalar": _Call(_scalar) for core in ("core", "_core")},
    **{f"numpy.{core}.numeric._frombuffer": _Call(_frombuffer) for core in ("core", "_core")},
    "numpy.dtype": _Call(_dtype),
    "numpy.ndarray": _NDARRAY,
    "copy_reg._reconstructor": _Call(_reconstructor),
    "copyreg._reconstructor": _Call(_reconstructor),
    "_codecs.encode": _Call(_encode),
    **{f"{builtins}.{name}": value for builtins in ("__builtin__", "builtins")
       for name, value in (("object", object), ("set", set), ("frozenset", frozenset))},
}


class _FlameUnpickler(pickle.Unpickler):
    """Resolves only the globals of a FLAME model file, to the stand-ins above."""

    def find_class(self, module: str, name: str) -> object:
        path = f"{module}.{name}"
        if module in CHUMPY_MODULES and _IDENTIFIER.match(name):
            return _stand_in(_ChumpyNode, path)
        if path in SPARSE_CLASSES:
            return _stand_in(_SparseMatrix, path, kind=SPARSE_CLASSES[path])
        if path in _GLOBALS:
            return _GLOBALS[path]
        raise PickleRefused(f"it references {path}, which no FLAME model holds: refused, nothing from the file ran")

    def persistent_load(self, pid: object) -> object:
        raise PickleRefused("it holds a persistent reference, which no FLAME model holds: refused")


# ------------------------------------------------------------------------------------------------ reading


# Containers deeper than this are no FLAME model (its deepest is a chumpy expression's state inside the dict).
_MAX_NESTING = 64


def _unwrapped(value: object, seen: dict[int, object], depth: int = 0) -> object:
    """`value` with every array and number stand-in replaced by the plain numpy value it holds (shared and
    self-referencing containers stay so: `seen` maps each visited container to its result)."""
    if isinstance(value, _Value):
        return value.value
    if isinstance(value, _PickledArray):
        if value.value is None:
            raise PickleRefused("a numpy array is never filled")
        return value.value
    if isinstance(value, _PickledDtype):
        return value.canonical()
    if not isinstance(value, dict | list | tuple | set | frozenset | _StandIn):
        return value
    if id(value) in seen:
        return seen[id(value)]
    if depth > _MAX_NESTING:
        raise PickleRefused(f"containers nested deeper than {_MAX_NESTING}")
    inner = lambda item: _unwrapped(item, seen, depth + 1)  # noqa: E731
    if isinstance(value, dict):
        seen[id(value)] = value
        items = [(inner(key), inner(item)) for key, item in value.items()]
        value.clear()
        value.update(items)
        return value
    if isinstance(value, list):
        seen[id(value)] = value
        value[:] = [inner(item) for item in value]
        return value
    if isinstance(value, _StandIn):
        seen[id(value)] = value
        if hasattr(value, "state"):
            inner(value.state)
        return value
    result = type(value)(inner(item) for item in value)
    seen[id(value)] = result
    return result


def _check_opcodes(data: bytes) -> None:
    """Walk the pickle's opcodes without running them (pickletools' pure reader), so that every length an opcode
    states is checked against the bytes present before the unpickler allocates for it."""
    for _opcode, _argument, _position in pickletools.genops(data):
        pass


def load_flame_pickle(path: str | Path) -> dict:
    """The model dict of a FLAME pickle, its chumpy/sparse objects as inert stand-ins; ImportFormatError if not."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_PICKLE_BYTES:
            raise ImportFormatError(f"{path}: {size} bytes, more than any FLAME model pickle "
                                    f"({MAX_PICKLE_BYTES >> 20} MiB at most)")
        data = path.read_bytes()
    except OSError as exc:
        raise ImportFormatError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    try:
        _check_opcodes(data)
        model = _unwrapped(_FlameUnpickler(io.BytesIO(data), encoding="latin1").load(), {})
    except PickleRefused as exc:
        raise ImportFormatError(_one_line(f"{path}: not a FLAME model pickle: {exc}")) from exc
    except Exception as exc:  # untrusted bytes: any failure of the unpickler means the file is unusable
        if data.startswith(b"PK"):
            raise ImportFormatError(f"{path}: a zip/npz archive, not a pickle (a FLAME npz needs no import)") from exc
        raise ImportFormatError(_one_line(f"{path}: not a readable pickle (truncated or damaged?): "
                                          f"{type(exc).__name__}: {exc}")) from exc
    if not isinstance(model, dict):
        raise ImportFormatError(f"{path}: the pickle holds a {type(model).__name__}, expected FLAME's dict of arrays")
    return model


def _one_line(message: str) -> str:
    """A refusal as the one line the CLI prints (exception texts from the unpickler may hold line breaks)."""
    return " ".join(message.split())


def _evaluate(value: object, where: str, depth: int = 0) -> np.ndarray:
    """A plain array from an ndarray or a chumpy node (a Ch's `x`, or Select/transpose/Reshape of one)."""
    if isinstance(value, np.ndarray):
        return value
    if depth > _MAX_DEPTH or not isinstance(value, _ChumpyNode) or not hasattr(value, "state"):
        kind = value.path if isinstance(value, _StandIn) else type(value).__name__
        raise ImportFormatError(f"{where} is a {kind}, not an array")
    state, path = value.state, value.path

    def operand(term: str) -> np.ndarray:
        return _evaluate(state.get(term), where, depth + 1)

    try:
        if path == "chumpy.ch.Ch":
            return operand("x")
        if path == "chumpy.reordering.Select":
            selected = operand("a").ravel()[np.asarray(state["idxs"], dtype=np.int64)]
            shape = state.get("preferred_shape")
            return selected if shape is None else selected.reshape(shape)
        if path == "chumpy.reordering.transpose":
            return np.transpose(operand("a"), state.get("axes"))
        if path == "chumpy.reordering.Reshape":
            return operand("a").reshape(state["newshape"])
    except (KeyError, IndexError, ValueError, TypeError) as exc:
        raise ImportFormatError(f"{where} ({path}) is inconsistent: {type(exc).__name__}: {exc}") from exc
    raise ImportFormatError(f"{where} is a chumpy expression ({path}), not a stored array")


def _sparse_dense(matrix: _SparseMatrix, where: str, expected: tuple[int, ...]) -> np.ndarray:
    """The dense array of a pickled CSC/CSR matrix, its declared shape checked against `expected` first."""
    state = getattr(matrix, "state", {})
    shape = state.get("_shape", state.get("shape"))
    if not (isinstance(shape, tuple) and len(shape) == 2 and all(isinstance(n, int | np.integer) for n in shape)):
        raise ImportFormatError(f"{where} ({matrix.path}) has no valid shape")
    shape = (int(shape[0]), int(shape[1]))
    _check_shape(where, shape, expected)
    try:
        data, indices, indptr = (np.asarray(state[k]) for k in ("data", "indices", "indptr"))
    except KeyError as exc:
        raise ImportFormatError(f"{where} ({matrix.path}) lacks its {exc.args[0]!r}") from exc
    major, minor = (shape[1], shape[0]) if matrix.kind == "csc" else shape
    ok = (indptr.shape == (major + 1,) and indices.ndim == 1 and data.shape == indices.shape
          and indices.dtype.kind in "iu" and indptr.dtype.kind in "iu" and data.dtype.kind in "biuf"
          and indptr[0] == 0 and indptr[-1] == indices.size and (np.diff(indptr) >= 0).all()
          and (indices.size == 0 or (indices.min() >= 0 and indices.max() < minor)))
    if not ok:
        raise ImportFormatError(f"{where} ({matrix.path}) has inconsistent data/indices/indptr")
    dense = np.zeros((major, minor), dtype=np.float64)
    rows = np.repeat(np.arange(major), np.diff(indptr))
    np.add.at(dense, (rows, indices.astype(np.int64)), data)  # duplicates add up, as scipy's todense does
    return dense.T if matrix.kind == "csc" else dense


def _describe(key: str, shape: tuple[int, ...], layout: FlameLayout) -> str:
    """What a wrong shape means, where it can be told: another model, or FLAME with other column counts."""
    if key in ("v_template", "shapedirs", "posedirs", "weights") and shape and shape[0] != layout.n_vertices:
        other = _OTHER_MODELS.get(shape[0])
        return f" ({shape[0]} vertices: {other}, not FLAME)" if other else ""
    if key == "shapedirs" and len(shape) == 3 and shape[:2] == (layout.n_vertices, 3):
        extra = shape[2] - layout.n_shape
        if extra <= 0:
            return " (identity shape only, no expression columns)"
        return (f" ({layout.n_shape} shape + {extra} expression columns; FLAME 2020 and FLAME 2023 have "
                f"{layout.n_shape} + {layout.n_expr})")
    return ""


def _check_shape(where: str, shape: tuple[int, ...], expected: tuple[int, ...], layout: FlameLayout | None = None,
                 key: str = "") -> None:
    if tuple(shape) != expected:
        hint = _describe(key, tuple(shape), layout) if layout is not None else ""
        raise ImportFormatError(f"{where} has shape {list(shape)}, expected {list(expected)}{hint}")


def flame_arrays_from_pickle(path: str | Path, layout: FlameLayout = FLAME_LAYOUT) -> dict[str, np.ndarray]:
    """FLAME_NPZ_KEYS arrays of a FLAME pickle (float32; f and kintree_table int64, J_regressor dense), checked
    against `layout`; ImportFormatError naming the field otherwise."""
    path = Path(path)
    model = load_flame_pickle(path)
    missing = [key for key in FLAME_NPZ_KEYS if key not in model]
    if missing:
        raise ImportFormatError(f"{path}: not a FLAME model: missing {', '.join(repr(k) for k in missing)} "
                                f"(it holds {', '.join(repr(k) for k in sorted(map(str, model))[:20]) or 'nothing'})")
    arrays = {}
    for key, expected in layout.expected().items():
        where = f"{path}: {key!r}"
        value = model[key]
        if isinstance(value, _SparseMatrix):
            array = _sparse_dense(value, where, expected)
        else:
            array = _evaluate(value, where)
        integer = key in ("f", "kintree_table")
        if array.dtype.kind not in ("iu" if integer else "biuf"):
            raise ImportFormatError(f"{where} has dtype {array.dtype}, expected {'integers' if integer else 'numbers'}")
        _check_shape(where, array.shape, expected, layout, key)
        arrays[key] = np.ascontiguousarray(array, dtype=np.int64 if integer else np.float32)
    return arrays


# ------------------------------------------------------------------------------------------------ writing


def detect_version(path: str | Path) -> str:
    """The FLAME release a model file is, from its name as the FLAME site ships it (the layouts are the same)."""
    name = Path(path).name.lower()
    for year in ("2023", "2020", "2019", "2017"):
        if year in name:
            variant = " Open" if "open" in name else " (no jaw rotation)" if "no_jaw" in name else ""
            return year + variant
    if Path(name).stem in ("generic_model", "female_model", "male_model"):
        return "2020"
    return "unknown"


def convert_flame_pkl(source: str | Path, output: str | Path, *, layout: FlameLayout = FLAME_LAYOUT,
                      version: str | None = None) -> FlameImport:
    """Write FLAME's pickle as the SDK's FLAME npz (np.savez, no pickles), verified through `load_flame_npz` before
    it replaces `output` (atomically: on any error `output` is left as it was)."""
    start = time.perf_counter()
    source, output = Path(source), Path(output)
    arrays = flame_arrays_from_pickle(source, layout)
    version = version or detect_version(source)
    extras = {VERSION_KEY: np.array(version), N_SHAPE_KEY: np.int64(layout.n_shape),
              N_EXPR_KEY: np.int64(layout.n_expr)}
    try:
        with atomic_path(output) as staged:
            with staged.path.open("wb") as handle:
                np.savez(handle, **arrays, **extras)
            check = load_flame_npz(staged.path, layout.n_shape, layout.n_expr, shape_columns=layout.n_shape)
    except OSError as exc:
        raise ImportFormatError(f"{output}: cannot write: {exc.strerror or exc}") from exc
    except CheckpointError as exc:  # the arrays have FLAME's shapes but not its content (weights, faces, ...)
        raise ImportFormatError(f"{source}: {exc}") from exc
    return FlameImport(output=output, version=version, n_vertices=check.n_vertices, n_faces=check.n_faces,
                       n_shape=check.n_shape, n_expr=check.n_expr, seconds=time.perf_counter() - start)


def read_flame_npz_info(path: str | Path) -> Mapping[str, object]:
    """The version and column counts `convert_flame_pkl` recorded in an npz (empty for other npz files)."""
    keys = (VERSION_KEY, N_SHAPE_KEY, N_EXPR_KEY)
    arrays = read_npz(path, ImportFormatError, "a FLAME npz", keys=keys)  # bounded by its bytes, never unpickled
    return {key: arrays[key].item() for key in keys if key in arrays and arrays[key].size == 1}
