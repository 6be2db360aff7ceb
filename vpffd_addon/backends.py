"""Where a solve runs: the backends as one registry (docs/architecture.md, "A new backend").

Each `Backend` declares what its steps can do (`capabilities`: the kinds of binding, "directions"
other than the lattice axes, "islands", "plain_measure"), whether it can run now (`available`) and
what else it asks of a solve (`accepts`: size limits, Auto's rules). NumPy's steps (the
reference) and the compiled kernels' (once `compiled.load()` succeeded) are registered here; the
GPU's compute shaders need Blender and are registered by the Blender layer
(operators/gpu_backend.py) while the extension is registered. `choose(preference, binding,
options)` turns the user's preference (AUTO, CPU, NUMPY, GPU) into a backend and the reason in
words; the solve then takes that backend's steps, and its `Solution.backend` names the backend
that ran.
"""
from dataclasses import dataclass
from typing import Callable, Optional

from . import compiled
from .cage import Cage
from .steps import CAPABILITIES, NumpySteps


def _always():
    return True, ""


@dataclass(frozen=True)
class Backend:
    """One place a solve can run. `steps(binding)`: the per-slot work for `solve.solve` (None for
    a backend whose caller makes its solver, e.g. the GPU's per binding); `available()` -> (ok,
    why not); `accepts(preference, binding, options, fresh)` -> (ok, why): what else it asks
    (None: nothing)."""
    name: str                       #: NUMPY, COMPILED, GPU
    label: str                      #: in words, as the panel says it
    device: str                     #: "CPU" or "GPU"
    capabilities: frozenset
    steps: Optional[Callable] = None
    available: Callable = _always
    accepts: Optional[Callable] = None


def needs(binding, options):
    """The capabilities a solve of `binding` with `options` (Binding.solve's keywords) asks for."""
    options = options or {}
    out = {"cage" if isinstance(binding.lattice, Cage) else "lattice"}
    if options.get("islands"):
        out.add("islands")
    if options.get("directions") is not None:
        out.add("directions")
    if not options.get("preserve_volume", True) or not (options.get("axes", "XYZ") or
                                                         options.get("directions") is not None):
        out.add("plain_measure")
    return out


def _compiled_available():
    return compiled.ready(), compiled.why()


def _compiled_accepts(preference, binding, options, fresh=False):
    if getattr(binding, "params", None) is None:
        # The compiled steps read the per-slot parameters of a compiled bind of a lattice.
        return False, ("cages solve with NumPy" if isinstance(binding.lattice, Cage)
                       else "this lattice's interpolation is solved with NumPy")
    return True, ""


NUMPY = Backend("NUMPY", "NumPy", "CPU", frozenset(CAPABILITIES | {"lattice", "cage"}), steps=NumpySteps)
COMPILED = Backend("COMPILED", "compiled", "CPU", frozenset(compiled.CompiledSteps.capabilities | {"lattice"}),
                   steps=compiled.CompiledSteps, available=_compiled_available, accepts=_compiled_accepts)

_registry = {}   # name -> Backend, in the order registered


def register(backend):
    """Add (or replace) `backend` under its name."""
    _registry[backend.name] = backend


def unregister(name):
    """Remove the backend called `name` (nothing when there is none)."""
    _registry.pop(name, None)


def get(name):
    """The registered backend called `name`, or None."""
    return _registry.get(name)


def registered():
    """The registered backends' names, in the order registered."""
    return tuple(_registry)


register(NUMPY)
register(COMPILED)


def usable(backend, preference, binding, options, fresh=False):
    """(ok, why not): whether `backend` can solve `binding` with `options` now."""
    if backend.accepts is not None:
        ok, why = backend.accepts(preference, binding, options, fresh)
        if not ok:
            return False, why
    missing = needs(binding, options) - backend.capabilities
    if missing:
        return False, f"the {backend.label} backend cannot do {', '.join(sorted(missing))}"
    return backend.available()


def choose(preference, binding, options=None, fresh=False):
    """(Backend, reason in words) for the user's `preference`: NUMPY (NumPy, the reference), CPU
    (the compiled kernels where they can run, else NumPy), GPU (the GPU where it can run, else as
    CPU) or AUTO (the GPU where its rules take it, else as CPU). `fresh`: the binding was made for
    this solve (Auto keeps such a one on the CPU). The reason says why the GPU was not taken
    (GPU, AUTO) or that the CPU was chosen. Never raises."""
    preference = str(preference).upper()
    options = options or {}
    if preference == "NUMPY":
        return NUMPY, "Backend is CPU (NumPy): the reference path"
    reason = "CPU chosen"
    if preference in ("GPU", "AUTO"):
        gpu = _registry.get("GPU")
        if gpu is None:
            reason = "the GPU path is not registered (it needs Blender's gpu module)"
        else:
            ok, reason = usable(gpu, preference, binding, options, fresh)
            if ok:
                return gpu, reason
    compiled_backend = _registry.get("COMPILED")
    if compiled_backend is not None and usable(compiled_backend, "CPU", binding, options)[0]:
        return compiled_backend, reason
    return NUMPY, reason


def cpu_preference(preference):
    """The user's `preference` for a solve that runs on the CPU whatever it says (a frame
    pipeline without a solver of the caller's): NUMPY stays NUMPY, every other becomes CPU."""
    return "NUMPY" if str(preference).upper() == "NUMPY" else "CPU"


def compiled_layout(preference):
    """Whether a binding made for `preference` is laid out with the compiled kernels (once they
    are loaded; bit for bit NumPy's layout): all but NUMPY, the reference path."""
    return cpu_preference(preference) != "NUMPY"


def default_steps(binding):
    """The steps a solve uses when none are given: the CPU's choice for `binding` (the compiled
    ones once `compiled.load()` succeeded, for a lattice bound by them; else NumPy's)."""
    return choose("CPU", binding)[0].steps(binding)
