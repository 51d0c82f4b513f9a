"""numba as the runtime's kernels use it: the on-disk cache where compiled kernels are kept, and OpenMP workers that
sleep when idle. Every module with numba kernels imports numba through here, so both hold before any kernel loads.
"""

from __future__ import annotations

import os
from pathlib import Path


def cache_dir() -> Path:
    """Where compiled kernels are cached: $NUMBA_CACHE_DIR if the user set it, else the user cache directory
    ($XDG_CACHE_HOME or ~/.cache, then gaussiantalker/numba)."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return Path(os.environ["NUMBA_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "gaussiantalker" / "numba"


def _configure_numba_cache() -> None:
    """Point numba's on-disk cache at `cache_dir` (only when the user has not chosen one) before any kernel loads."""
    import numba

    if not os.environ.get("NUMBA_CACHE_DIR") and not numba.config.CACHE_DIR:
        numba.config.CACHE_DIR = str(cache_dir())


_configure_numba_cache()

# Idle OpenMP workers sleep instead of spinning (unless the user chose a policy): numba's parallel kernels share
# the cores with onnxruntime's graphs, and spinning workers starve them (measured: docs/bench/renderers.md,
# "Threads that wait"). Read by the OpenMP runtime when numba first loads it.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numba  # noqa: E402  (after the cache directory is set)
from llvmlite import ir  # noqa: E402
from numba import njit, prange  # noqa: E402
from numba.core import cgutils, types  # noqa: E402
from numba.extending import intrinsic  # noqa: E402


@intrinsic
def claim(typingctx, counter):
    """Inside a kernel: counter[0] += 1 as one atomic step, returning the value before (int64 [1] counter).

    Threads that take work items by `claim` share the work as they finish it (dynamic scheduling), where numba's
    parallel loops hand each thread a fixed slice: a thread whose core is also running other work (the pipeline's
    deformation) then takes fewer items instead of holding the others back. numba offers no atomic operation on the
    CPU, so this emits LLVM's `atomicrmw add` itself."""
    if not (isinstance(counter, types.Array) and counter.dtype == types.int64 and counter.ndim == 1):
        return None

    def codegen(context, builder, signature, args):
        array_type = signature.args[0]
        array = context.make_array(array_type)(context, builder, args[0])
        first = cgutils.get_item_pointer(context, builder, array_type, array, [context.get_constant(types.intp, 0)])
        return builder.atomic_rmw("add", first, context.get_constant(types.int64, 1), "monotonic")

    return types.int64(counter), codegen


@intrinsic
def prefetch(typingctx, array, row):
    """Inside a kernel: ask the CPU to bring the cache line of array[row, 0] in, for reading, without waiting for it
    (LLVM's `llvm.prefetch`; numba has no such call). A row index out of range is harmless: a prefetch never faults.
    For loops that read rows in an order the CPU's own prefetchers cannot guess (a tile's list of Gaussians)."""
    if not (isinstance(array, types.Array) and array.ndim == 2 and isinstance(row, types.Integer)):
        return None

    def codegen(context, builder, signature, args):
        array_type = signature.args[0]
        data = context.make_array(array_type)(context, builder, args[0])
        index = context.cast(builder, args[1], signature.args[1], types.intp)
        address = cgutils.get_item_pointer(context, builder, array_type, data,
                                           [index, context.get_constant(types.intp, 0)], wraparound=False)
        # LLVM names its intrinsics by pointer type: "p0" where pointers are opaque (llvmlite >= 0.44), else "p0i8"
        if str(address.type) != "ptr":
            address = builder.bitcast(address, ir.IntType(8).as_pointer())
        name = "llvm.prefetch." + ("p0" if str(address.type) == "ptr" else "p0i8")
        i32 = ir.IntType(32)
        function = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(ir.VoidType(), [address.type, i32, i32, i32]), name)
        # read (0), keep in all cache levels (3), a data cache (1)
        builder.call(function, [address, i32(0), i32(3), i32(1)])
        return context.get_dummy_value()

    return types.none(array, row), codegen


__all__ = ["cache_dir", "claim", "njit", "numba", "prange", "prefetch"]
