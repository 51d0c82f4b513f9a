"""Fuzzer of the FLAME pickle reader (exporter/imports/formats/flame_pkl.py): mutated FLAME-layout pickles, each of
which must load into arrays that own exactly their file's bytes, or be refused with one line naming the file.

Run as a script so that a crash (a signal) ends only this process and the test that started it can name the case:

    python tests/flame_fuzz.py --seed 1 --cases 400 [--keep DIR]

prints one line per failing case and a JSON summary last; exits 1 if any case failed. Two kinds of mutation:

* value level: the model dict is edited before pickling, with forged reductions the real writers never emit
  (dtype states with subarrays, fields, item sizes or byte orders that do not match their type string; array states
  whose shape, dtype and bytes disagree; `_frombuffer` and `scalar` arguments likewise; broken chumpy and sparse
  states; values of the wrong kind);
* opcode level: the bytes of a valid pickle are cut at opcode boundaries and spans are deleted, repeated, swapped or
  moved; integer and length arguments are replaced with edge values (0, -1, 2**31 - 1, ...); globals are renamed
  to other allowed or forbidden ones; BUILD opcodes are inserted after arbitrary objects; bytes are flipped.
"""

from __future__ import annotations

import argparse
import io
import json
import pickle
import pickletools
import struct
import sys
import tempfile
import traceback
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from flame_pickles import (  # noqa: E402
    CscMatrix,
    FlameSpec,
    GlobalRef,
    chumpy_class,
    flame_model,
    flame_pickle_dict,
    py2_dumps,
)

from gaussiantalker.exporter.imports.formats.flame_pkl import FlameLayout, convert_flame_pkl, load_flame_pickle  # noqa: E402
from gaussiantalker.sdk.errors import ImportFormatError  # noqa: E402

SPEC = FlameSpec(n_vertices=12, n_faces=10, n_shape=4, n_expr=3)
LAYOUT = FlameLayout(n_vertices=SPEC.n_vertices, n_faces=SPEC.n_faces, n_shape=SPEC.n_shape, n_expr=SPEC.n_expr)
EDGE_INTS = [0, 1, -1, 2, 3, 8, 255, 256, 2**15, 2**16 - 1, 2**31 - 1, -(2**31), 2**32 - 1, 2**40, 2**62, -(2**62)]
ALLOWED_GLOBALS = [("numpy", "dtype"), ("numpy", "ndarray"), ("numpy.core.multiarray", "_reconstruct"),
                   ("numpy._core.multiarray", "scalar"), ("numpy._core.numeric", "_frombuffer"),
                   ("copy_reg", "_reconstructor"), ("_codecs", "encode"), ("__builtin__", "set"),
                   ("__builtin__", "object"), ("chumpy.ch", "Ch"), ("chumpy.reordering", "Select"),
                   ("scipy.sparse.csc", "csc_matrix")]
FORBIDDEN_GLOBALS = [("os", "system"), ("__builtin__", "eval"), ("numpy", "frombuffer"), ("numpy.lib", "format"),
                     ("numpy.core.multiarray", "frombuffer"), ("builtins", "getattr")]
TYPE_STRINGS = ["f8", "f4", "<f8", ">f4", "i8", "u4", "b1", "?", "S", "S5", "U", "U3", "c16", "(3,)f8", "f8,i4",
                "O", "V8", "M8", "i16", "f8\x00", b"f8", b"(100000000,)f8", 5, None, ""]


class Reduced:
    """Pickles as whatever reduction it is given (a forged callable, arguments and BUILD state)."""

    def __init__(self, *reduction: object) -> None:
        self.reduction = reduction

    def __reduce__(self) -> tuple:
        return self.reduction


def dtype(spec: object = "f8", state: object = (3, "<", None, None, None, -1, -1, 0)) -> Reduced:
    """numpy.dtype(spec) with `state` as its BUILD (a real writer's state by default)."""
    return Reduced(GlobalRef("numpy", "dtype"), (spec, 0, 1), state)


def reconstructed(state: object) -> Reduced:
    """numpy's `_reconstruct` followed by a BUILD of `state` (an ndarray's (version, shape, dtype, fortran, raw))."""
    return Reduced(GlobalRef("numpy.core.multiarray", "_reconstruct"), (GlobalRef("numpy", "ndarray"), (0,), b"b"),
                   state)


def frombuffer(raw: object, dtype_: object, shape: object, order: object = "C") -> Reduced:
    return Reduced(GlobalRef("numpy._core.numeric", "_frombuffer"), (raw, dtype_, shape, order))


def subarray_attack_value(n_sub: int = 100_000_000, item_size: int = 8) -> Reduced:
    """The subarray attack: a float64 dtype whose BUILD state gives it an `n_sub`-element subarray but an item size
    of `item_size` bytes, then `_frombuffer` of `item_size` bytes as that dtype in shape (1, n_sub), so a reader
    that trusts the dtype views `n_sub * 8` bytes of memory through an `item_size`-byte buffer."""
    forged = dtype("f8", (3, "|", (dtype("f8"), (n_sub,)), None, None, item_size, 1, 0))
    return frombuffer(b"A" * item_size, forged, (1, n_sub))


def subarray_attack_pickle(n_sub: int = 100_000_000, item_size: int = 8) -> bytes:
    """`subarray_attack_value` alone, pickled the way Python 3 pickles bytes at protocol 2 (by `_codecs.encode`)."""
    return modern_dumps_protocol(subarray_attack_value(n_sub, item_size), 2)


class ModernPickler(pickle._Pickler):
    """Writes what Python 3 with newer numpy writes at protocol 5: arrays by `_frombuffer`, names by GLOBAL."""

    dispatch = dict(pickle._Pickler.dispatch)

    def save_global(self, obj: object, name: str | None = None) -> None:
        if isinstance(obj, GlobalRef):
            module, name = obj.module, obj.name
        else:
            module, name = obj.__module__, name or obj.__qualname__
        self.write(pickle.GLOBAL + f"{module}\n{name}\n".encode())
        self.memoize(obj)

    dispatch[GlobalRef] = save_global

    def reducer_override(self, obj: object) -> object:
        if isinstance(obj, np.ndarray):
            return GlobalRef("numpy._core.numeric", "_frombuffer"), (np.ascontiguousarray(obj).tobytes(), obj.dtype,
                                                                     obj.shape, "C")
        if isinstance(obj, np.dtype):
            return GlobalRef("numpy", "dtype"), (obj.str[1:], False, True), (3, obj.str[0], None, None, None, -1, -1, 0)
        return NotImplemented


def modern_dumps_protocol(obj: object, protocol: int) -> bytes:
    buffer = io.BytesIO()
    ModernPickler(buffer, protocol=protocol).dump(obj)
    return buffer.getvalue()


def modern_dumps(obj: object) -> bytes:
    return modern_dumps_protocol(obj, 5)


# ------------------------------------------------------------------------------------------------ value level


def _random_shape(rng: np.random.Generator) -> object:
    choices: list[object] = [(), (0,), (3,), (4, 3), (-1,), (2**40,), (3, 2**62), (2**31, 2**31), "x", [3], (1.5,),
                             (True,), tuple(range(40)), 7]
    return choices[rng.integers(len(choices))]


def _random_raw(rng: np.random.Generator) -> object:
    n = int(rng.choice([0, 1, 7, 8, 24, 96, 1000]))
    kinds: list[object] = [bytes(rng.integers(0, 256, n, dtype=np.uint8)), "A" * n, [1.0] * min(n, 5), n, None,
                           bytearray(n)]
    return kinds[rng.integers(len(kinds))]


def _random_dtype(rng: np.random.Generator) -> object:
    spec = TYPE_STRINGS[rng.integers(len(TYPE_STRINGS))]
    if rng.random() < 0.3:
        return dtype(spec)
    state = [3, "<", None, None, None, -1, -1, 0]
    slot = int(rng.integers(8))
    values: list[object] = [dtype("f8"), (dtype("f8"), (int(rng.choice(EDGE_INTS[:12])),)), ("a", "b"),
                            {"a": (dtype("f8"), 0)}, int(rng.choice(EDGE_INTS)), "x", ">", "|", None, 4, 16]
    state[slot] = values[rng.integers(len(values))]
    forged: object = tuple(state)
    if rng.random() < 0.15:
        forged = tuple(state[: int(rng.integers(0, 11))]) if rng.random() < 0.7 else {"x": 1}
    return dtype(spec, forged)


def _forged_array(rng: np.random.Generator) -> object:
    """An array reduction whose parts may disagree."""
    kind = rng.integers(4)
    if kind == 0:
        state = [1, _random_shape(rng), _random_dtype(rng), bool(rng.integers(2)), _random_raw(rng)]
        if rng.random() < 0.2:
            state = state[int(rng.integers(0, 2)):] if rng.random() < 0.5 else [*state, 0]
        if rng.random() < 0.1:
            state[0] = int(rng.choice([0, 2, -1]))
        return reconstructed(tuple(state))
    if kind == 1:
        order = ["C", "F", "A", 1, None][rng.integers(5)]
        return frombuffer(_random_raw(rng), _random_dtype(rng), _random_shape(rng), order)
    if kind == 2:
        return Reduced(GlobalRef("numpy.core.multiarray", "scalar"), (_random_dtype(rng), _random_raw(rng)))
    return Reduced(GlobalRef("numpy.core.multiarray", "_reconstruct"),
                   ([GlobalRef("numpy", "dtype"), GlobalRef("chumpy.ch", "Ch"), 3][rng.integers(3)], (0,), b"b"),
                   (1, (2,), dtype("f8"), False, b"\x00" * 16))


def _value_edit(rng: np.random.Generator) -> Callable[[dict], None]:
    """One edit of the model dict (value level)."""
    key = ["v_template", "f", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table", "J",
           "bs_style"][rng.integers(9)]
    kind = int(rng.integers(7))

    def edit(model: dict) -> None:
        target = model[key]
        if kind in (0, 1):  # an array replaced by a forged one (inside its chumpy node where it has one)
            forged = _forged_array(rng)
            if hasattr(target, "__dict__") and "x" in target.__dict__ and kind == 0:
                target.x = forged
            else:
                model[key] = forged
        elif kind == 2:  # the subarray attack inside a model
            model[key] = subarray_attack_value(int(rng.choice([2, 1000, 10**8])), int(rng.choice([1, 8, 16])))
        elif kind == 3:  # broken chumpy expressions
            select = chumpy_class("chumpy.reordering.Select")
            reshape = chumpy_class("chumpy.reordering.Reshape")
            transpose = chumpy_class("chumpy.reordering.transpose")
            base = flame_model(SPEC)["shapedirs"]
            options = [
                select({"a": model["J"], "idxs": np.array([10**9, -(10**9)]), "preferred_shape": None}),
                select({"a": model["J"], "idxs": np.arange(4), "preferred_shape": (2**40, 2**40)}),
                reshape({"a": model["J"], "newshape": (-1, 2**62)}),
                transpose({"a": model["J"], "axes": (0, 0, 5)}),
                select({"a": select({"a": model["J"]}), "idxs": "x"}),
                transpose({"a": base, "axes": None}),
            ]
            model[key] = options[rng.integers(len(options))]
        elif kind == 4:  # broken sparse matrices
            sparse = CscMatrix(flame_model(SPEC)["J_regressor"])
            field = ["_shape", "indices", "indptr", "data"][rng.integers(4)]
            values: list[object] = [(2**31, 2**31), (-1, 5), np.array([2**31 - 1], dtype=np.int32),
                                    np.array([0, -5, 3]), np.zeros(2**10), "x", None, _forged_array(rng)]
            setattr(sparse, field, values[rng.integers(len(values))])
            model["J_regressor"] = sparse
        elif kind == 5:  # the wrong kind of value
            model[key] = [None, 3, "text", [1.0, 2.0], {"x": 1}, {1, 2}, b"\x00" * 8, (1, 2)][rng.integers(8)]
        else:  # a reference loop
            loop: list = []
            loop.append(loop)
            model[key] = loop if rng.random() < 0.5 else chumpy_class("chumpy.ch.Ch")({"x": model})

    return edit


# ------------------------------------------------------------------------------------------------ opcode level

_INT_ARGS = {"BININT": "<i", "BININT1": "<B", "BININT2": "<H", "BINPUT": "<B", "BINGET": "<B", "LONG_BINPUT": "<I",
             "LONG_BINGET": "<I", "MEMOIZE": None}
_LENGTH_PREFIXED = {"SHORT_BINSTRING": "<B", "BINSTRING": "<i", "SHORT_BINUNICODE": "<B", "BINUNICODE": "<I",
                    "SHORT_BINBYTES": "<B", "BINBYTES": "<I", "BINBYTES8": "<Q", "BYTEARRAY8": "<Q",
                    "BINUNICODE8": "<Q"}


def _spans(data: bytes) -> list[tuple[str, int, int]]:
    """(opcode name, start, end) of each opcode, as far as the bytes parse (an earlier mutation may have broken
    them), the rest one span."""
    ops = []
    try:
        ops.extend((op.name, pos) for op, _, pos in pickletools.genops(data))
    except Exception:  # noqa: BLE001 - pickletools reports a broken stream by any exception type
        pass
    parsed_to = ops[-1][1] + 1 if ops else 0
    if parsed_to < len(data):
        ops.append(("RAW", parsed_to))
    return [(name, pos, ops[i + 1][1] if i + 1 < len(ops) else len(data)) for i, (name, pos) in enumerate(ops)]


def _opcode_mutation(data: bytes, rng: np.random.Generator) -> bytes:
    spans = _spans(data)
    if not spans:
        return data
    body = spans[1:-1] if len(spans) > 2 else spans  # keep PROTO and STOP most of the time
    name, start, end = body[rng.integers(len(body))]
    kind = int(rng.integers(9))
    if kind == 0:  # delete a span
        return data[:start] + data[end:]
    if kind == 1:  # repeat a span
        return data[:end] + data[start:end] + data[end:]
    if kind == 2:  # swap two spans
        _, start2, end2 = body[rng.integers(len(body))]
        (a0, a1), (b0, b1) = sorted([(start, end), (start2, end2)])
        if a1 > b0:
            return data
        return data[:a0] + data[b0:b1] + data[a1:b0] + data[a0:a1] + data[b1:]
    if kind == 3:  # an integer argument set to an edge value
        ints = [s for s in body if s[0] in _INT_ARGS and _INT_ARGS[s[0]]]
        if not ints:
            return data
        name, start, end = ints[rng.integers(len(ints))]
        fmt = _INT_ARGS[name]
        size = struct.calcsize(fmt)
        value = int(rng.choice(EDGE_INTS)) % (1 << (8 * size))
        if fmt == "<i" and value >= 1 << 31:
            value -= 1 << 32
        return data[: start + 1] + struct.pack(fmt, value) + data[start + 1 + size:]
    if kind == 4:  # a length field that lies (the data stay)
        strings = [s for s in body if s[0] in _LENGTH_PREFIXED]
        if not strings:
            return data
        name, start, end = strings[rng.integers(len(strings))]
        fmt = _LENGTH_PREFIXED[name]
        size = struct.calcsize(fmt)
        old = struct.unpack(fmt, data[start + 1: start + 1 + size])[0]
        value = int(rng.choice([0, old - 1, old + 1, old * 2, 2**31 - 1, int(rng.choice(EDGE_INTS))]))
        value %= 1 << (8 * size)
        if fmt == "<i" and value >= 1 << 31:
            value -= 1 << 32
        return data[: start + 1] + struct.pack(fmt, value) + data[start + 1 + size:]
    if kind == 5:  # a global renamed
        globals_ = [s for s in spans if s[0] == "GLOBAL"]
        if not globals_:
            return data
        _, start, end = globals_[rng.integers(len(globals_))]
        pool = ALLOWED_GLOBALS if rng.random() < 0.8 else FORBIDDEN_GLOBALS
        module, name = pool[rng.integers(len(pool))]
        return data[:start] + b"c" + f"{module}\n{name}\n".encode() + data[end:]
    if kind == 6:  # a BUILD after an arbitrary object
        states = [b"}", b")", b"N", b"(K\x03U\x01|NNNJ\xff\xff\xff\xffJ\xff\xff\xff\xffK\x00t",
                  b"(K\x01(K\x02tcnumpy\ndtype\n(U\x02f8K\x00K\x01tR(K\x03U\x01<NNNJ\xff\xff\xff\xffJ\xff\xff\xff"
                  b"\xffK\x00tbI00\nU\x04AAAAt", b"}U\x01xK\x01s"]
        return data[:end] + states[rng.integers(len(states))] + b"b" + data[end:]
    if kind == 7:  # flipped bytes
        out = bytearray(data)
        for _ in range(int(rng.integers(1, 8))):
            at = int(rng.integers(len(out)))
            out[at] ^= 1 << int(rng.integers(8))
        return bytes(out)
    return data[: spans[rng.integers(len(spans))][1]]  # cut at an opcode boundary


# ------------------------------------------------------------------------------------------------ cases


def base_pickles(seed: int) -> list[bytes]:
    """Valid FLAME-layout pickles of the three kinds the reader meets (Python 2 at protocols 2 and 1, Python 3
    with newer numpy at protocol 5)."""
    spec = FlameSpec(n_vertices=SPEC.n_vertices, n_faces=SPEC.n_faces, n_shape=SPEC.n_shape, n_expr=SPEC.n_expr,
                     seed=seed)
    model = flame_pickle_dict(flame_model(spec))
    return [py2_dumps(model, 2), py2_dumps(model, 1), modern_dumps(model)]


def make_case(index: int, seed: int) -> bytes:
    """Case `index` of the run with `seed`: a value-level or opcode-level mutation (or both) of a valid pickle."""
    rng = np.random.default_rng([seed, index])
    if rng.random() < 0.45:
        model = flame_pickle_dict(flame_model(SPEC))
        for _ in range(int(rng.integers(1, 3))):
            _value_edit(rng)(model)
        writer = [lambda m: py2_dumps(m, 2), lambda m: py2_dumps(m, 1), modern_dumps][rng.integers(3)]
        try:
            data = writer(model)
        except (pickle.PicklingError, RecursionError, TypeError, ValueError, AttributeError):
            data = py2_dumps(flame_pickle_dict(flame_model(SPEC)), 2)
        if rng.random() < 0.2:
            data = _opcode_mutation(data, rng)
        return data
    bases = base_pickles(0)
    data = bases[rng.integers(len(bases))]
    for _ in range(int(rng.integers(1, 4))):
        data = _opcode_mutation(data, rng)
        if not data:
            break
    return data


def array_problems(model: object, file_size: int) -> list[str]:
    """What is wrong with the arrays of a loaded model: an array that does not own its memory, a dtype that is not
    plain, or more bytes than the file holds (each array's bytes come from the file once)."""
    problems, seen, stack = [], set(), [model]
    while stack:
        value = stack.pop()
        if id(value) in seen:
            continue
        seen.add(id(value))
        if isinstance(value, np.ndarray):
            if value.base is not None or not value.flags.owndata:
                problems.append(f"an array of shape {value.shape} is a view of other memory")
            if value.dtype.fields is not None or value.dtype.subdtype is not None or value.dtype.hasobject:
                problems.append(f"an array of dtype {value.dtype!r} is not plain")
            if value.nbytes > file_size:
                problems.append(f"an array of {value.nbytes} bytes from a {file_size}-byte file")
        elif isinstance(value, dict):
            stack.extend(value.keys())
            stack.extend(value.values())
        elif isinstance(value, list | tuple | set | frozenset):
            stack.extend(value)
        elif hasattr(value, "state"):
            stack.append(value.state)
    return problems


def check_case(path: Path, output: Path) -> tuple[str, str]:
    """('loaded' | 'refused', detail), or ('FAILED', why) when the reader broke its promise."""
    size = path.stat().st_size
    try:
        model = load_flame_pickle(path)
    except ImportFormatError as exc:
        return refusal_outcome(path, exc)
    except Exception as exc:  # the reader's promise: nothing but ImportFormatError
        return "FAILED", f"load_flame_pickle raised {type(exc).__name__}: {exc}\n{traceback.format_exc()}"
    problems = array_problems(model, size)
    if problems:
        return "FAILED", "; ".join(problems)
    try:
        convert_flame_pkl(path, output, layout=LAYOUT)
    except ImportFormatError as exc:
        return refusal_outcome(path, exc)
    except Exception as exc:
        return "FAILED", f"convert_flame_pkl raised {type(exc).__name__}: {exc}\n{traceback.format_exc()}"
    return "loaded", ""


def refusal_outcome(path: Path, exc: ImportFormatError) -> tuple[str, str]:
    message = str(exc)
    if "\n" in message or not message.startswith(f"{path}: "):
        return "FAILED", f"the refusal is not one line naming the file: {message!r}"
    return "refused", message


def run(seed: int, cases: int, keep: Path | None = None) -> dict:
    """Run `cases` cases; print each failure; return the summary."""
    counts = {"loaded": 0, "refused": 0, "FAILED": 0}
    failures = []
    with tempfile.TemporaryDirectory() as scratch:
        folder = keep or Path(scratch)
        folder.mkdir(parents=True, exist_ok=True)
        for index in range(cases):
            path = folder / f"case-{seed}-{index}.pkl"
            path.write_bytes(make_case(index, seed))
            print(f"case {index}", file=sys.stderr, flush=True)  # the last one named is the one a crash hit
            outcome, detail = check_case(path, folder / "out.npz")
            counts[outcome] += 1
            if outcome == "FAILED":
                failures.append({"case": index, "why": detail})
                print(f"FAILED case {index} (seed {seed}): {detail}", flush=True)
            elif keep is None:
                path.unlink()
    return {"seed": seed, "cases": cases, **counts, "failures": failures}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--cases", type=int, default=400)
    parser.add_argument("--keep", type=Path, help="keep every case's file in this folder")
    args = parser.parse_args()
    summary = run(args.seed, args.cases, args.keep)
    print(json.dumps(summary))
    sys.exit(1 if summary["failures"] else 0)


if __name__ == "__main__":
    main()
