"""A small shared thread pool: NumPy releases the GIL in the per-block products, gathers and ufuncs,
so splitting blocks and faces over a few threads uses the other cores (NOTES.md section 5)."""
import os
import threading
from concurrent.futures import ThreadPoolExecutor

#: Threads a binding splits its work over (memory-bound kernels gain little beyond a few).
WORKERS = max(1, min(os.cpu_count() or 1, 4))
#: Below this many vertices one thread is faster than handing work around.
MIN_VERTS_PER_PART = 16384

_pool = None
_lock = threading.Lock()


def run(fn, parts):
    """[fn(p) for p in parts], on the pool when there is more than one part."""
    if len(parts) == 1:
        return [fn(parts[0])]
    global _pool
    with _lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(WORKERS, thread_name_prefix="vpffd")
    return list(_pool.map(fn, parts))


def split(n, n_verts):
    """Contiguous slices covering range(n), one per part for a mesh of n_verts vertices."""
    k = max(1, min(WORKERS, n_verts // MIN_VERTS_PER_PART, n))
    edges = [n * i // k for i in range(k + 1)]
    return [slice(edges[i], edges[i + 1]) for i in range(k)]
