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


__all__ = ["cache_dir", "claim", "njit", "numba", "prange"]
