"""The compiled kernels inside Blender (docs/performance.md, "Compiled kernels").

numba holds the GIL while it compiles (seconds), which would freeze Blender's window. So the first
solve of a session starts a separate Python process that compiles the kernels into numba's cache in
the extension's user folder (`bpy.utils.extension_path_user`: never the extension's own folder,
which may be read-only and is replaced on update), while VP-FFD goes on solving with NumPy; when it
is done, the kernels are loaded from that cache here (well under a second) and the next solves use
them. A later session finds them cached. Without a window (`blender -b`, farms) there is nothing to
freeze: the kernels are compiled or loaded in the process itself.

Nothing here runs at register time, and nothing here raises into Blender: where numba is missing
(the universal package) or unusable, VP-FFD solves with NumPy and `status()` says why.
"""
import importlib.util
import logging
import os
import subprocess
import sys

import bpy

from .. import vpffd_addon as vp

log = logging.getLogger(__name__)

_ROOT_PACKAGE = __package__.rsplit(".", 1)[0]
_EXTENSION_DIR = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
_state = {"status": "idle", "why": "", "proc": None}

#: The compiling process: the core alone (no bpy), imported from the extension's own folder under
#: the very module name it has in Blender (its parent packages made empty, so that the extension's
#: own __init__, which needs bpy, does not run): numba's cache keys the kernels by source file and
#: refers to their module by name, so the two processes read each other's cache.
_CHILD = ("import importlib, os, sys, types\n"
          "if hasattr(os, 'nice'):\n"
          "    os.nice(10)\n"
          "ext_dir, root = sys.argv[1], sys.argv[2]\n"
          "parts = root.split('.')\n"
          "for i in range(1, len(parts) + 1):\n"
          "    m = types.ModuleType('.'.join(parts[:i]))\n"
          "    m.__path__ = [ext_dir] if i == len(parts) else []\n"
          "    sys.modules[m.__name__] = m\n"
          "compiled = importlib.import_module(root + '.vpffd_addon.compiled')\n"
          "ok = compiled.load()\n"
          "print(compiled.why() or 'compiled')\n"
          "sys.exit(0 if ok else 1)\n")


def status():
    """(state, words): "idle" (not asked yet), "compiling", "ready" or "off" (NumPy solves; the
    words say why)."""
    if vp.compiled.ready():
        return "ready", "compiled kernels"
    if _state["status"] == "ready":              # a script switched them off since
        return "off", vp.compiled.why()
    return _state["status"], _state["why"]


def cache_dir():
    """numba's cache folder for this extension, in its user folder (made when missing)."""
    return bpy.utils.extension_path_user(_ROOT_PACKAGE, path="numba-cache", create=True)


def _off(why):
    _state.update(status="off", why=why, proc=None)
    log.info("solving with NumPy: %s", why)


def start(in_process=None):
    """Make the compiled kernels available for this session (once; later calls return at once).
    `in_process`: compile here rather than in a separate process (default: without a window).
    Never raises."""
    if _state["status"] != "idle" or vp.compiled.ready():
        return
    try:
        if importlib.util.find_spec("numba") is None:
            _off("numba is not installed (this package has no wheels for this platform)")
            return
        # numba reads NUMBA_CACHE_DIR when it is first imported in this process; the setting is
        # process-wide. Another extension may have set it first (then that folder is the cache),
        # or imported numba without it (then its configuration is given the folder now).
        cache = os.environ.setdefault("NUMBA_CACHE_DIR", cache_dir())
        numba = sys.modules.get("numba")
        if numba is not None and not getattr(numba.config, "CACHE_DIR", ""):
            numba.config.CACHE_DIR = cache
        if bpy.app.background if in_process is None else in_process:
            if vp.compiled.load():
                _state.update(status="ready", why="")
            else:
                _off(vp.compiled.why())
            return
        # The compile takes seconds of one core: a process of lower priority (nice 10, or below
        # normal on Windows), with one thread for everything it links, so that Blender's window
        # keeps its frame rate on a machine of two cores.
        env = dict(os.environ, NUMBA_CACHE_DIR=cache, NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1",
                   OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1",
                   PYTHONPATH=os.pathsep.join(p for p in sys.path if p and os.path.isdir(p)))
        flags = getattr(subprocess, "BELOW_NORMAL_PRIORITY_CLASS", 0)
        _state["proc"] = subprocess.Popen(
            [sys.executable, "-c", _CHILD, _EXTENSION_DIR, _ROOT_PACKAGE], env=env, stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, creationflags=flags)
        _state.update(status="compiling", why="compiling the kernels in a separate process; "
                                             "NumPy solves meanwhile")
        bpy.app.timers.register(_poll, first_interval=0.5)
    except Exception as exc:  # never into Blender: NumPy solves
        _off(f"the compiled kernels could not be started ({type(exc).__name__}: {exc})")


def _poll():
    """Timer: once the compiling process is done, load its kernels here. Returns the seconds to
    the next look, or None when done."""
    proc = _state["proc"]
    if proc is None:
        return None
    if proc.poll() is None:
        return 0.5
    output = (proc.stdout.read() if proc.stdout else "").strip()
    if proc.returncode != 0:
        _off(output.splitlines()[-1] if output else f"the compiling process ended with {proc.returncode}")
        return None
    try:
        ready = vp.compiled.load()
    except Exception as exc:
        ready = False
        output = f"{type(exc).__name__}: {exc}"
    if ready:
        _state.update(status="ready", why="", proc=None)
        log.info("compiled kernels loaded")
        for window in getattr(bpy.context.window_manager, "windows", []):
            for area in window.screen.areas:
                area.tag_redraw()
    else:
        _off(vp.compiled.why() or output)
    return None


def reset():
    """Forget this session's attempt (a running compile is stopped); the next `start()` tries
    again. The kernels stay loaded if they were."""
    proc = _state["proc"]
    if proc is not None and proc.poll() is None:
        proc.kill()
        proc.wait()
    _state.update(status="idle", why="", proc=None)


def unregister():
    reset()
