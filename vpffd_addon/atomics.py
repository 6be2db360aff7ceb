"""Counters that the parts of one compiled pass share across threads (docs/performance.md,
"Fewer hand-overs").

Two passes that follow each other over the same parts (the forward pass, then the gradient pass
that reads its coordinates) can run in one hand-over per part when every part, after its first
pass, waits until all parts have made theirs: a counter of arrivals. And the thread that handed
the parts out can see that every part is done without sleeping until the last worker wakes it: a
counter of parts done, which the kernels add to as their last act. numba has no atomic operations
on the CPU, so `define()` writes them as intrinsics: LLVM's atomic add, an acquire load, and the
processor's hint that a thread is spinning (x86's `pause`, which leaves the core's other hardware
thread its share; nothing elsewhere). The waits that use them are `solve_kernels.wait_count` and
`arrive_and_wait`.

Every wait is bounded by a count of looks (`spins_for`): a wait that runs out returns False and
its caller takes the slow, sure way (the part skips its second pass, which the caller then runs
itself; the caller sleeps on the workers' events). So nothing can hang, and nothing spins while no
pass is running. Nothing here imports numba on import.

numba caches a compiled kernel keyed on the file it is written in: the fused kernels of
`solve_kernels.py` carry these intrinsics inside them, so after a change here, numba's cache must
be cleared (or solve_kernels.py touched) for them to be compiled anew.
"""
import platform
import time

import numpy as np

# A shared counter array `sync` (int64): [0] parts arrived after their first pass, [1] parts done,
# [2 + k] whether part k ran its second pass (1) or ran out of spins at the barrier (0),
# [2 + n + k] what part k's second pass returned (to_verts: its coordinates that are not finite).
ARRIVED, DONE, HEAD = 0, 1, 2

#: The most looks a microsecond `spins_for` believes (the loop makes about 20 to 4,000 on the
#: processors measured; more would mean a clock too coarse to time it).
MOST_LOOKS_PER_US = 20000


def new_sync(n_parts):
    """A fresh counter array for one fused pass over `n_parts` parts: (2 + 2 n,) int64 zeros."""
    return np.zeros(HEAD + 2 * n_parts, np.int64)


def define():
    """{name: intrinsic} for int64 arrays: `fetch_add(a, i, v)` (atomically a[i] += v, returns
    the old value; its writer's earlier writes are seen by whoever reads the sum with
    `load_acquire`), `load_acquire(a, i)` and `spin_hint()` (x86's `pause`; nothing on other
    processors)."""
    from llvmlite import ir
    from numba import types
    from numba.core import cgutils
    from numba.extending import intrinsic

    def _pointer(context, builder, aryty, ary_value, index):
        ary = context.make_array(aryty)(context, builder, ary_value)
        return cgutils.get_item_pointer(context, builder, aryty, ary, [index])

    @intrinsic
    def fetch_add(typingctx, a, i, v):
        def codegen(context, builder, signature, args):
            ptr = _pointer(context, builder, signature.args[0], args[0], args[1])
            return builder.atomic_rmw("add", ptr, args[2], "seq_cst")
        return types.int64(a, types.intp, types.int64), codegen

    @intrinsic
    def load_acquire(typingctx, a, i):
        def codegen(context, builder, signature, args):
            ptr = _pointer(context, builder, signature.args[0], args[0], args[1])
            return builder.load_atomic(ptr, "acquire", 8)
        return types.int64(a, types.intp), codegen

    x86 = platform.machine().lower() in ("x86_64", "amd64", "i386", "i686", "x86")

    @intrinsic
    def spin_hint(typingctx):
        def codegen(context, builder, signature, args):
            if x86:
                fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.VoidType(), []),
                                                    "llvm.x86.sse2.pause")
                builder.call(fn, [])
            return context.get_dummy_value()
        return types.none(), codegen

    return {"fetch_add": fetch_add, "load_acquire": load_acquire, "spin_hint": spin_hint}


def spins_for(wait_count, microseconds):
    """{name: looks} for {name: microseconds}: how many looks of `wait_count(sync, i, n, looks)`
    take about that long on this machine: timed on a counter that never reaches its target, with
    more looks until one timing lasts a millisecond (so that a coarse clock cannot make it read
    zero), the fastest of three; at least 1,000 looks, and no more than `MOST_LOOKS_PER_US` a
    microsecond."""
    sync = np.zeros(1, np.int64)
    n = 1 << 12
    wait_count(sync, 0, 1, 1)                          # (compiled by now; warm)
    while True:
        best = float("inf")
        for _ in range(3):
            t = time.perf_counter()
            wait_count(sync, 0, 1, n)
            best = min(best, time.perf_counter() - t)
        if best >= 1e-3 or n >= 1 << 22:
            break
        n *= 4
    per_us = min(n / max(best * 1e6, 1e-3), MOST_LOOKS_PER_US)
    return {name: max(1000, int(per_us * us)) for name, us in microseconds.items()}
