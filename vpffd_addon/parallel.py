"""Fixed worker threads for the per-frame kernels.

NumPy releases the GIL in its gathers, small matrix products and ufuncs, so splitting blocks and
faces over a few threads uses the other cores (docs/performance.md). The kernels are memory-bound:
part k of every array always goes to the same thread (part 0 to the caller), so the data a thread
wrote in one step is still in its core's cache when it reads it in the next.
"""
import os
import queue
import threading

#: Threads a binding splits its work over (memory-bound kernels gain little beyond a few).
WORKERS = max(1, min(os.cpu_count() or 1, 4))
#: Below this many vertices per part, handing work to another thread costs more than it saves.
MIN_VERTS_PER_PART = 65536

_workers = []
_lock = threading.Lock()


class _Worker:
    def __init__(self, k):
        self.jobs = queue.SimpleQueue()
        threading.Thread(target=self._loop, name=f"vpffd-{k}", daemon=True).start()

    def _loop(self):
        while True:
            fn, arg, done = self.jobs.get()
            try:
                done.append((True, fn(arg)))
            except BaseException as exc:  # handed back to the caller, never lost in the thread
                done.append((False, exc))
            done_event = done[0]
            done_event.set()


def run(fn, parts):
    """[fn(p) for p in parts]; part 0 runs in the calling thread, part k in worker k."""
    if len(parts) == 1:
        return [fn(parts[0])]
    with _lock:
        while len(_workers) < len(parts) - 1:
            _workers.append(_Worker(len(_workers) + 1))
    pending = []
    for k, p in enumerate(parts[1:]):
        box = [threading.Event()]
        _workers[k].jobs.put((fn, p, box))
        pending.append(box)
    results = [fn(parts[0])]
    for box in pending:
        box[0].wait()
        ok, value = box[1]
        if not ok:
            raise value
        results.append(value)
    return results


def split(n, n_verts):
    """Contiguous slices covering range(n), one per part for a mesh of n_verts vertices."""
    k = max(1, min(WORKERS, n_verts // MIN_VERTS_PER_PART, n))
    edges = [n * i // k for i in range(k + 1)]
    return [slice(edges[i], edges[i + 1]) for i in range(k)]
