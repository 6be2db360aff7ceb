"""Probes of the test process itself."""
import time


def cpu_while_asleep(seconds=0.1):
    """Milliseconds of this process's CPU time spent while its main thread sleeps `seconds`: what
    other threads of the process (e.g. BLAS threads left spinning) burn meanwhile."""
    c0 = time.process_time()
    time.sleep(seconds)
    return (time.process_time() - c0) * 1e3
