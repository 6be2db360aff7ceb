"""Fixed worker threads for the per-frame kernels.

NumPy and the compiled kernels release the GIL, so splitting blocks and faces over threads uses
every core the process may run on (docs/performance.md, "Every core"). Part k of every array
always goes to the same thread (part 0 to the caller), so the data a thread wrote in one step is
still in its core's cache when it reads it in the next. An idle worker waits on its queue: it
holds no core between frames.
"""
import math
import os
import queue
import threading


def cores():
    """The cores this process may run on: its affinity where the platform tells it, and no more
    than a Linux container's CPU quota allows (a render farm's container may see every core of
    its host and be given the time of two: threads beyond that only wait on each other)."""
    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        n = os.cpu_count() or 1
    quota = cpu_quota()
    return max(1, min(n, math.ceil(quota)) if quota is not None else n)


def _read(path):
    try:
        with open(path, encoding="ascii") as fh:
            return fh.read()
    except (OSError, ValueError):
        return None


def cpu_quota(read=_read):
    """The CPUs' worth of time a Linux cgroup's quota gives this process (e.g. 2.0), or None where
    none is set or none can be read: cgroup v2's cpu.max ("200000 100000", or "max 100000"), else
    v1's cpu.cfs_quota_us over cpu.cfs_period_us (-1: none). `read(path)`: the file's text or None."""
    text = read("/sys/fs/cgroup/cpu.max")
    try:
        if text is not None:
            quota, period = text.split()[:2]
        else:
            quota, period = read("/sys/fs/cgroup/cpu/cpu.cfs_quota_us"), read("/sys/fs/cgroup/cpu/cpu.cfs_period_us")
        if quota is None or period is None or quota == "max" or float(quota) <= 0:
            return None
        return max(float(quota) / float(period), 1e-3)
    except (ValueError, ZeroDivisionError):
        return None


#: The cores this process may use (`cores()`, read once: it opens files where a cgroup is set).
CORES = cores()
#: Threads a binding splits its work over: every core the process may use.
WORKERS = CORES
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


_handed = [0]       # passes whose parts are with the workers now (`busy`)


def busy():
    """Whether some thread's pass is with the workers now (two solves at once: a pass that waits
    for its parts at a barrier would wait for the other solve's)."""
    return _handed[0] > 0


def _hand_out(fn, parts):
    """Part k (k >= 1) to worker k: the boxes their results will be in. The caller hands the pass
    back with `_done()` once it stops waiting for it."""
    with _lock:
        _handed[0] += 1
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
    try:
        results = [fn(parts[0])]
        return results + _collect(pending)
    finally:
        _done()


def run_counted(fn, parts, finished):
    """fn(p) for every part, as `run` hands them out, for kernels that count the parts done
    themselves and leave their results in arrays: after part 0, `finished()` (a bounded wait in
    compiled code on that count, True once every part is done) spares this thread its wait for
    the last worker to wake it (docs/performance.md, "Fewer hand-overs"); where it returns False,
    this thread waits for the workers as `run` does (and raises what a part raised). Returns
    whether `finished()` saw them done."""
    if len(parts) == 1:
        fn(parts[0])
        return True
    pending = _hand_out(fn, parts)
    try:
        fn(parts[0])
        if finished():
            return True
        _collect(pending)
        return False
    finally:
        _done()


def _done():
    with _lock:
        _handed[0] -= 1


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
    global WORKERS, CORES
    if n is None:
        CORES = cores()
    previous, WORKERS = WORKERS, CORES if n is None else max(1, int(n))
    return previous


def split(n, n_verts):
    """Contiguous slices covering range(n), one per part for a mesh of n_verts vertices."""
    k = max(1, min(WORKERS, n_verts // MIN_VERTS_PER_PART, n))
    edges = [n * i // k for i in range(k + 1)]
    return [slice(edges[i], edges[i + 1]) for i in range(k)]
