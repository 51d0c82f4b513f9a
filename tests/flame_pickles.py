"""FLAME model pickles written the way the licensed files are (Python 2, chumpy, scipy), without chumpy or scipy.

A real `generic_model.pkl` is a dict whose arrays are chumpy `Ch` objects (their array is `x` in their pickled
`__dict__`, beside an empty `_dirty_vars` set and a few flags), a scipy `csc_matrix` `J_regressor` (its `__dict__`:
`_shape`, `data`, `indices`, `indptr`, ...) and plain numpy arrays, with Python-2 byte strings throughout. The
stand-in classes below carry the real class paths, and `Py2Pickler` writes str/bytes as Python-2 strings and
globals under their Python-2 module names, so the bytes reference exactly the globals a real file does.
"""

from __future__ import annotations

import io
import pickle
import struct
from dataclasses import dataclass

import numpy as np

UINT32_MAX = 4294967295
# Python-3 module names the Python-2 files spell differently.
PY2_MODULES = {"builtins": "__builtin__", "copyreg": "copy_reg"}


class GlobalRef:
    """A global written by name only (module, name), e.g. numpy.core.multiarray._reconstruct."""

    def __init__(self, module: str, name: str) -> None:
        self.module, self.name = module, name

    def __call__(self, *args: object) -> None:  # pickle's writer asks that a reduce function be callable
        raise TypeError(f"{self.module}.{self.name} is written by name only")


class Ch:
    """Pickles as chumpy.ch.Ch: its state is chumpy's `__dict__` without `_parents`/`_cache`."""

    def __init__(self, x: np.ndarray) -> None:
        self.__dict__.update(x=x, _dirty_vars=set(), _itr=None, _depends_on_deps={}, _make_dense=False,
                             _make_sparse=False)


Ch.__module__, Ch.__qualname__ = "chumpy.ch", "Ch"


class ChumpyNode:
    """Pickles as another chumpy class (`path`), with the given state."""

    def __init__(self, state: dict) -> None:
        self.__dict__.update(state)


class CscMatrix:
    """Pickles as scipy.sparse.csc.csc_matrix: scipy's `__dict__` for a CSC matrix."""

    def __init__(self, dense: np.ndarray) -> None:
        rows, cols = dense.shape
        indices, data, indptr = [], [], [0]
        for j in range(cols):
            nz = np.nonzero(dense[:, j])[0]
            indices.extend(nz.tolist())
            data.extend(dense[nz, j].tolist())
            indptr.append(len(indices))
        self.__dict__.update(_shape=(rows, cols), maxprint=50, format="csc", has_sorted_indices=1,
                             indices=np.asarray(indices, dtype=np.int32), indptr=np.asarray(indptr, dtype=np.int32),
                             data=np.asarray(data, dtype=np.float64))


CscMatrix.__module__, CscMatrix.__qualname__ = "scipy.sparse.csc", "csc_matrix"


def chumpy_class(path: str) -> type:
    """A stand-in class that pickles as `path` (e.g. chumpy.reordering.Select)."""
    module, _, name = path.rpartition(".")
    return type(name, (ChumpyNode,), {"__module__": module, "__qualname__": name})


class Py2Pickler(pickle._Pickler):
    """Writes what Python 2's cPickle wrote: str/bytes as byte strings, numpy arrays through
    numpy.core.multiarray._reconstruct with their bytes in the state, globals under Python-2 module names."""

    dispatch = dict(pickle._Pickler.dispatch)

    def _save_py2_string(self, obj: str | bytes) -> None:
        raw = obj.encode("latin1") if isinstance(obj, str) else obj
        if len(raw) < 256:
            self.write(pickle.SHORT_BINSTRING + bytes([len(raw)]) + raw)
        else:
            self.write(pickle.BINSTRING + struct.pack("<i", len(raw)) + raw)
        self.memoize(obj)

    def _save_global_ref(self, obj: GlobalRef) -> None:
        self.write(pickle.GLOBAL + f"{obj.module}\n{obj.name}\n".encode())
        self.memoize(obj)

    def save_global(self, obj: object, name: str | None = None) -> None:
        module = PY2_MODULES.get(obj.__module__, obj.__module__)
        self._save_global_ref(GlobalRef(module, name or obj.__qualname__))

    dispatch[str] = _save_py2_string
    dispatch[bytes] = _save_py2_string
    dispatch[GlobalRef] = _save_global_ref

    def reducer_override(self, obj: object) -> object:
        if isinstance(obj, np.ndarray):
            dtype = obj.dtype
            state = (1, obj.shape, dtype, False, np.ascontiguousarray(obj).tobytes())
            return GlobalRef("numpy.core.multiarray", "_reconstruct"), (GlobalRef("numpy", "ndarray"), (0,), b"b"), \
                state
        if isinstance(obj, np.generic):
            return GlobalRef("numpy.core.multiarray", "scalar"), (obj.dtype, obj.tobytes())
        if isinstance(obj, np.dtype):
            return GlobalRef("numpy", "dtype"), (obj.str[1:], 0, 1), (3, obj.str[0], None, None, None, -1, -1, 0)
        return NotImplemented


def py2_dumps(obj: object, protocol: int = 2) -> bytes:
    """`obj` pickled as Python 2 did (protocol 2 by default: chumpy objects by NEWOBJ; 1: copy_reg._reconstructor)."""
    buffer = io.BytesIO()
    Py2Pickler(buffer, protocol=protocol).dump(obj)
    return buffer.getvalue()


@dataclass
class FlameSpec:
    """A FLAME-layout model with `n_vertices` vertices (5023 and 9976 faces for FLAME's own)."""

    n_vertices: int = 40
    n_faces: int = 60
    n_shape: int = 300
    n_expr: int = 100
    seed: int = 0


def flame_model(spec: FlameSpec) -> dict[str, np.ndarray]:
    """The model's arrays as a FLAME file holds them (float64, uint32 faces and kintree, root parent uint32 max)."""
    rng = np.random.default_rng(spec.seed)
    v = spec.n_vertices
    weights = rng.random((v, 5)) + 0.1
    regressor = np.where(rng.random((5, v)) < 0.2, rng.random((5, v)), 0.0)
    regressor[:, 0] += 0.1  # every joint regresses from at least one vertex
    return {
        "v_template": rng.normal(0, 0.1, (v, 3)),
        "f": rng.integers(0, v, (spec.n_faces, 3)).astype(np.uint32),
        "shapedirs": rng.normal(0, 1e-3, (v, 3, spec.n_shape + spec.n_expr)),
        "posedirs": rng.normal(0, 1e-3, (v, 3, 36)),
        "J_regressor": regressor / regressor.sum(axis=1, keepdims=True),
        "weights": weights / weights.sum(axis=1, keepdims=True),
        "kintree_table": np.array([[UINT32_MAX, 0, 1, 1, 1], [0, 1, 2, 3, 4]], dtype=np.int64),
    }


def flame_pickle_dict(arrays: dict[str, np.ndarray]) -> dict:
    """The dict a FLAME pickle holds: chumpy arrays, a CSC J_regressor, numpy f/kintree_table, and FLAME's extras."""
    model = {key: Ch(arrays[key]) for key in ("v_template", "shapedirs", "posedirs", "weights")}
    model.update(f=arrays["f"], kintree_table=arrays["kintree_table"], J_regressor=CscMatrix(arrays["J_regressor"]),
                 J=Ch(arrays["J_regressor"] @ arrays["v_template"]), bs_style="lbs", bs_type="lrotmin")
    return model


def write_flame_pickle(path, spec: FlameSpec | None = None, *, protocol: int = 2, edit=None) -> dict[str, np.ndarray]:
    """Write a FLAME pickle at `path`; `edit(model_dict)` may change it first. Returns the arrays put in."""
    arrays = flame_model(spec or FlameSpec())
    model = flame_pickle_dict(arrays)
    if edit is not None:
        edit(model)
    path.write_bytes(py2_dumps(model, protocol))
    return arrays
