"""Counters that the parts of one compiled pass share across threads (docs/performance.md,
"Fewer hand-overs").

Two passes that follow each other over the same parts (the forward pass, then the gradient pass
that reads its coordinates) can run in one hand-over per part when every part, after its first
pass, waits until all parts have made theirs: a counter of arrivals. And the thread that handed
the parts out can see that every part is done without sleeping until the last worker wakes it: a
counter of parts done, which the kernels add to as their last act. numba has no atomic operations
on the CPU, so `define(numba)` writes them as intrinsics (LLVM's atomic add and acquire load).

Every wait here is bounded by a count of spins (`spins_for`): a wait that runs out returns False
and its caller takes the slow, sure way (the part skips its second pass, which the caller then
runs itself; the caller sleeps on the workers' events). So nothing here can hang, and nothing
spins while no pass is running. Nothing here imports numba on import.
"""
import time

import numpy as np

# A shared counter array `sync` (int64): [0] parts arrived after their first pass, [1] parts done,
# [2 + k] whether part k ran its second pass (1) or ran out of spins at the barrier (0),
# [2 + n + k] what part k's second pass returned (to_verts: its coordinates that are not finite).
ARRIVED, DONE, HEAD = 0, 1, 2


def new_sync(n_parts):
    """A fresh counter array for one fused pass over `n_parts` parts: (2 + 2 n,) int64 zeros."""
    return np.zeros(HEAD + 2 * n_parts, np.int64)


def define(numba, njit):
    """{name: function}: the intrinsics `fetch_add(a, i, v)` (atomically a[i] += v, returns the
    old value) and `load_acquire(a, i)` (a[i], with every write its writer made before its add),
    for int64 arrays, bound in this module's namespace, and the two waits below compiled by
    `njit` (where numba finds and caches them, as `solve_kernels.define` does)."""
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

    space = globals()
    space["fetch_add"], space["load_acquire"] = fetch_add, load_acquire
    space["wait_count"] = njit(_SOURCE["wait_count"])
    space["arrive_and_wait"] = njit(_SOURCE["arrive_and_wait"])
    return {"fetch_add": fetch_add, "load_acquire": load_acquire, "wait_count": space["wait_count"],
            "arrive_and_wait": space["arrive_and_wait"]}


def wait_count(sync, i, n, spins):
    # Whether sync[i] reached n within `spins` looks.
    for _ in range(spins):
        if load_acquire(sync, i) >= n:  # noqa: F821 (bound by `define`)
            return True
    return False


def arrive_and_wait(sync, n, spins):
    # This part has made its first pass: count it, then wait (bounded) for the other parts.
    fetch_add(sync, ARRIVED, 1)  # noqa: F821 (bound by `define`)
    return wait_count(sync, ARRIVED, n, spins)


#: The plain functions, as written (`define` rebinds their names to compiled ones).
_SOURCE = {"wait_count": wait_count, "arrive_and_wait": arrive_and_wait}


def spins_for(wait_count, microseconds):
    """How many looks of `wait_count` take about `microseconds` on this machine (measured once,
    on a counter that never reaches its target; at least 1,000)."""
    sync = np.zeros(1, np.int64)
    n = 1 << 16
    wait_count(sync, 0, 1, n)                          # (compiled by now; warm)
    best = float("inf")
    for _ in range(3):
        t = time.perf_counter()
        wait_count(sync, 0, 1, n)
        best = min(best, time.perf_counter() - t)
    per_us = n / max(best * 1e6, 1e-3)
    return max(1000, int(per_us * microseconds))
