"""Fixed worker threads for the per-frame kernels.

NumPy and the compiled kernels release the GIL, so splitting blocks and faces over threads uses
every core the process may run on (docs/performance.md, "Every core"). Part k of every array
always goes to the same thread (part 0 to the caller), so the data a thread wrote in one step is
still in its core's cache when it reads it in the next. An idle worker waits on its queue: it
holds no core between frames.
"""
import os
import queue
import threading


def cores():
    """The cores this process may run on (its affinity where the platform tells it)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


#: Threads a binding splits its work over: every core the process may use.
WORKERS = cores()
#: Below this many vertices per part, handing work to another thread costs more than it saves
#: (a hand-over costs tens of microseconds; a compiled pass over 8,192 slots about as much).
MIN_VERTS_PER_PART = 8192

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


def _hand_out(fn, parts):
    """Part k (k >= 1) to worker k: the boxes their results will be in."""
    with _lock:
        while len(_workers) < len(parts) - 1:
            _workers.append(_Worker(len(_workers) + 1))
    pending = []
    for k, p in enumerate(parts[1:]):
        box = [threading.Event()]
        _workers[k].jobs.put((fn, p, box))
        pending.append(box)
    return pending


def run(fn, parts):
    """[fn(p) for p in parts]; part 0 runs in the calling thread, part k in worker k."""
    if len(parts) == 1:
        return [fn(parts[0])]
    pending = _hand_out(fn, parts)
    results = [fn(parts[0])]
    return results + _collect(pending)


def run_counted(fn, parts, finished):
    """fn(p) for every part, as `run` hands them out, for kernels that count the parts done
    themselves and leave their results in arrays: after part 0, `finished()` (a bounded wait in
    compiled code on that count, True once every part is done) spares this thread its wait for
    the last worker to wake it (docs/performance.md, "Fewer hand-overs"); where it returns False,
    this thread waits for the workers as `run` does (and raises what a part raised)."""
    if len(parts) == 1:
        fn(parts[0])
        return
    pending = _hand_out(fn, parts)
    fn(parts[0])
    if not finished():
        _collect(pending)


def _collect(pending):
    results = []
    for box in pending:
        box[0].wait()
        ok, value = box[1]
        if not ok:
            raise value
        results.append(value)
    return results


def set_workers(n=None):
    """Split new bindings over n threads (None: every core), e.g. to measure how a kernel scales.
    Returns the previous count. Bindings made before keep their parts."""
    global WORKERS
    previous, WORKERS = WORKERS, cores() if n is None else max(1, int(n))
    return previous


def split(n, n_verts):
    """Contiguous slices covering range(n), one per part for a mesh of n_verts vertices."""
    k = max(1, min(WORKERS, n_verts // MIN_VERTS_PER_PART, n))
    edges = [n * i // k for i in range(k + 1)]
    return [slice(edges[i], edges[i + 1]) for i in range(k)]
