"""GPU path of the volume-preserving solve: Blender's `gpu` compute shaders (docs/design.md, "The
GPU dispatch plan"). This module is what the rest of the extension imports: whether the GPU path
can run and is chosen (`available`, `choose`), its entry in the core's registry of backends
(`register`), and the names of its parts:

- `gpu_shaders`: the compute-shader sources (GLSL) and the texture layout they assume;
- `gpu_device`: the calls of Blender's `gpu` module (context, kernels compiled, textures, dispatch);
- `gpu_solver`: `GPUSolver`, a binding uploaded once and a solve's per-slot work on it, and
  `supports`, what it does.

Kernels and buffers only: the solve itself (closed forms, shares, pins, mobility, warnings and
errors) is `vpffd_addon.solve.solve`, the one driver, which asks a steps object for the per-slot
work (`vpffd_addon.steps`); here that object runs compute shaders on textures uploaded once per
binding. The arrays uploaded are built and tested in the core (`vpffd_addon.gpu_layout`).
What stays on the CPU and why: directions other than the lattice axes (their gradient needs the
projected coordinates of every slot), per-island rows (one transposed product per island), cages
(no fixed blocks of control points). `gpu` is imported lazily, never at import or register time.

What crosses the bus per direction: up, the N control-point offsets when they changed (one RGBA32F
texture); down, one float pair per 256 slots (the last level of the tree sums runs in float64 on
the CPU) and the N values of the transposed product; at the end the final coordinates (V x 4
floats).
"""
import os


def _beside(*names):
    """The modules `names` of this folder when this file is loaded by its path, outside the
    extension's package (tests and benchmarks do: the `operators` package needs Blender). They
    are imported as submodules of a stand-in package over this folder, made once per name this
    module is loaded under, so that their own `from .` imports work and they exist once."""
    import importlib
    import sys
    import types
    package = __name__ + "_parts"
    if package not in sys.modules:
        stand_in = types.ModuleType(package, f"the modules beside {__name__} (operators/gpu_backend.py)")
        stand_in.__path__ = [os.path.dirname(os.path.abspath(__file__))]
        sys.modules[package] = stand_in
    return [importlib.import_module(f"{package}.{name}") for name in names]


try:
    from ..vpffd_addon import backends as _vbackends
    from . import gpu_device, gpu_shaders, gpu_solver
except ImportError:  # loaded outside the extension package (tests, benchmarks)
    from vpffd_addon import backends as _vbackends
    gpu_device, gpu_shaders, gpu_solver = _beside("gpu_device", "gpu_shaders", "gpu_solver")

# The names the rest of the extension, the tests and the benchmarks take from here. (`choose`,
# `available`, `renderer`, `is_software_renderer` and `AUTO_MIN_VERTS` are this module's own:
# tests replace them here.)
GPUUnavailable = gpu_device.GPUUnavailable
GPUSolver = gpu_solver.GPUSolver
supports = gpu_solver.supports
make_texture, read_texture, release = gpu_device.make_texture, gpu_device.read_texture, gpu_device.release
TW = gpu_shaders.TW

#: Auto uses the GPU from this many vertices on (below, uploads and dispatch overhead dominate).
AUTO_MIN_VERTS = 50000
#: Renderers on which the GPU path is slower than NumPy (software rasterisers).
SOFTWARE_RENDERERS = ("llvmpipe", "softpipe", "swiftshader", "software rasterizer", "lavapipe")


# ------------------------------------------------------------------------------------------------
# Availability and backend choice


def available():
    """(ok, reason): whether the GPU path can run here now. Never raises.

    Fails in background mode before a GPU backend exists ("GPU functions for drawing are not
    available in background mode"), without compute support, off the main thread, or when the
    kernels do not compile; the reason says which."""
    try:
        gpu_device.check_context()
        gpu_device.kernels(64, 4, 16)
        return True, "GPU compute shaders are available (" + renderer() + ")"
    except GPUUnavailable as exc:
        return False, str(exc)
    except Exception as exc:  # never raise from here
        return False, f"GPU check failed: {type(exc).__name__}: {exc}"


def renderer():
    """The GPU renderer's name, or '' when unknown. Never raises."""
    try:
        return str(gpu_device.gpu_module().platform.renderer_get())
    except Exception:
        return ""


def is_software_renderer():
    """True on software OpenGL (Mesa llvmpipe and the like), where the GPU path is slow."""
    name = renderer().lower()
    return any(s in name for s in SOFTWARE_RENDERERS)


def choose(backend, n_verts, options=None, binding=None, fresh=False):
    """(use_gpu, reason) for a backend setting 'AUTO', 'CPU' or 'GPU'. Never raises.

    AUTO: the GPU when it is available, supports the options, the mesh has at least
    AUTO_MIN_VERTS vertices, the renderer is a real GPU (not software OpenGL), and the binding is
    not `fresh` (made for this solve and not yet used by an earlier one: an input that moves
    relative to the lattice is embedded anew on every frame, and uploading each embedding costs
    several CPU solves; docs/performance.md, "The GPU path on a hardware GPU").
    GPU: the GPU whenever it can run; otherwise the CPU, with the reason."""
    backend = str(backend).upper()
    if backend == "CPU":
        return False, "CPU chosen"
    ok, why = supports(options, binding)
    if not ok:
        return False, why
    if backend == "AUTO" and n_verts < AUTO_MIN_VERTS:
        return False, "Auto chose the CPU: a mesh this small solves faster there"
    if backend == "AUTO" and fresh:
        return False, ("Auto chose the CPU: the mesh was just bound or moved through the lattice, "
                       "and sending it to the GPU costs more than one solve saves there; it goes "
                       "to the GPU once it keeps its place")
    ok, why = available()
    if not ok:
        return False, why
    if backend == "AUTO" and is_software_renderer():
        return False, f"Auto chose the CPU: this machine draws with software OpenGL ({renderer()}), slower than the CPU"
    return True, why


# ------------------------------------------------------------------------------------------------
# Registration


def _accepts(preference, binding, options, fresh=False):
    """The GPU entry's own rules (`choose`: the options and sizes it supports, Auto's)."""
    return choose(preference, binding.n_verts, options, binding, fresh)


def register():
    """Register the GPU path in the core's registry of backends (`vpffd_addon/backends.py`):
    lattice bindings, lattice axes, one volume row; it makes its solver per binding
    (`GPUSolver`), so it lends no steps to the CPU's solve."""
    _vbackends.register(_vbackends.Backend(
        "GPU", "GPU", "GPU", frozenset({"lattice"}) | gpu_solver.CAPABILITIES,
        available=available, accepts=_accepts))


def unregister():
    """Take the GPU path out of the registry and drop its kernels (on the main thread)."""
    _vbackends.unregister("GPU")
    release()


