"""The cached state of each bound deformer (`Bound`): the frame pipeline with its caches, the last
solve's key, result and overlay, the GPU solver. Nothing in it is needed for a frame's result to be
right: it only saves work (docs/stack.md); `forget` and `invalidate` drop it."""
from .. import vpffd_addon as vp
from ..vpffd_addon import backends
from . import gpu_backend
from .control_read import is_control
from .status import deformer_of, forget_status

states = {}   # deformer key (object session_uid, modifier uid) -> Bound


def state_of(target):
    """The cached `Bound` of deformer `target` (or of a mesh object's first deformer), or None."""
    return states.get(deformer_of(target).key)


def forget(obj=None, d=None):
    """Drop cached bindings and the status shown: of deformer `d`, of every deformer of `obj`,
    or of all."""
    keys = [k for k in states if obj is None and d is None or (d is not None and k == d.key)
            or (obj is not None and k[0] == obj.session_uid)]
    for k in keys:
        states.pop(k).free()
    forget_status(obj, None if d is None else d.key)


def relink_after_undo(d, objects):
    """Point bound deformer `d` back at the lattice it lost to Delete when undo brought that lattice
    back. VP-FFD lets go of a deleted lattice in its update handler, after Delete's undo step was
    written, so the step before Delete holds the same object data as the step of Delete and
    Blender's undo keeps the object as it is in memory, link cleared (Blender clears its own
    modifier's link inside the operator, before the step is written). `objects`: bpy.data.objects.
    Returns True when the link was restored."""
    state = states.get(d.key)
    s = d.settings
    if state is None or not state.deleted or s.lattice is not None or not s.is_bound:
        return False
    back = objects.get(state.deleted)
    if not is_control(back) or not any(True for _ in back.users_scene):
        return False
    s.lattice = back                # its update callback points the modifier's input at it too
    state.deleted = None
    return True


def invalidate():
    """Make the next update of every object solve again (after undo, redo): the solves' inputs
    may be restored to other values, the helpers to other offsets. Caches stay."""
    for state in states.values():
        state.signature = None
        state.written = None


class Bound:
    """Cached per-deformer state: the frame pipeline (topology and binding caches), the faces of
    the slot's input, the last solve's signature, result and overlay. Nothing in it is needed for
    a frame's result to be right: it only saves work (docs/stack.md)."""

    def __init__(self):
        self.pipeline = vp.Pipeline(solver=self._solve)
        self.faces = self.faces_key = None
        self.signature = None
        self.result = None
        self.output = None      # (V, 3) float32 slot output of the last solve
        self.moved = 0.0        # the largest offset of the last solve (tells Apply from removal)
        self.written = None     # offsets last written to the solver helper
        self.wrote = False      # whether the last update wrote new offsets (update_scene)
        self.overlay = None
        self.gpu = None         # GPUSolver for the current binding, made on first GPU use
        self.gpu_binding = None
        self.last_binding = None  # the binding of the last solve (Auto uploads one used twice)
        self.backend = ("CPU", "")
        self.matrix = None      # object -> lattice space of the last solve
        self.falloff_box = None  # world corners (8, 3) of the falloff's outer box, for the overlay
        self.orientation = 1.0  # -1 while the lattice mirrors space (folds count against it)
        self.encloses_nothing = False  # the last input had no volume to keep (`_evaluate`)
        self.costs = {}         # last solve's seconds per (path, vertices, options) for Auto
        self.settings = None
        self.deleted = None     # name of the lattice that the user deleted, for the panel
        self.cage_model = self.cage_key = None

    @property
    def binding(self):
        return self.pipeline.binding

    @property
    def points(self):
        return None if self.result is None else self.result.points

    def free(self):
        if self.gpu is not None:
            self.gpu.free()
            self.gpu = self.gpu_binding = None

    def _solve(self, binding, P, options):
        """The pipeline's solver: the backend that the core's registry chooses for the settings'
        preference (`vpffd_addon/backends.py`); for Auto, the GPU only while this mesh's GPU
        solves measure no slower than its CPU solves; the CPU's when the GPU fails."""
        s = self.settings
        fresh = binding is not self.gpu_binding and binding is not self.last_binding
        self.last_binding = binding
        chosen, why = backends.choose(s.backend, binding, options, fresh)
        if s.backend == "NUMPY":
            self.backend = ("CPU", "")
            return binding.solve(P, steps=chosen.steps, **options)
        key = (binding.n_verts, options["axes"], options["directions"] is not None, options["islands"])
        if chosen.device == "GPU" and s.backend == "AUTO":
            use_gpu, why = self._measured(key, why)
            if not use_gpu:
                chosen = backends.choose("CPU", binding, options)[0]
        if chosen.device == "GPU":
            try:
                if self.gpu is None or self.gpu_binding is not binding:
                    self.free()
                    self.gpu, self.gpu_binding = gpu_backend.GPUSolver(binding), binding
                sol = self.gpu.solve(P, **options)
                self.backend = ("GPU", why)
                self.costs[("GPU",) + key] = sol.seconds
                return sol
            except gpu_backend.GPUUnavailable as exc:
                self.free()
                why = f"the GPU failed, using the CPU: {exc}"
                chosen = backends.choose("CPU", binding, options)[0]
        self.backend = ("CPU", why)
        sol = binding.solve(P, steps=chosen.steps, **options)
        self.costs[("CPU",) + key] = sol.seconds
        return sol

    def _measured(self, key, why):
        """Auto's last word once both paths have solved this mesh with these options: (use_gpu,
        reason). The GPU stays in use while its last solve was no slower than the CPU's."""
        gpu, cpu = self.costs.get(("GPU",) + key), self.costs.get(("CPU",) + key)
        if gpu is None or cpu is None or gpu <= cpu:
            return True, why
        return False, (f"Auto chose the CPU: it solved this mesh in {1e3 * cpu:.1f} ms, the GPU "
                       f"in {1e3 * gpu:.1f} ms")
