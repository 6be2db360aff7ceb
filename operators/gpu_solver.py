"""The GPU path's solver: a lattice binding uploaded to the GPU once (`GPUSolver`) and the per-slot
work of a solve on it as compute-shader dispatches (`_GPUSteps`: `vpffd_addon.steps`' interface),
which the one solve driver (`vpffd_addon.solve.solve`) asks for; `supports`: what it does.

The solve itself (closed forms, shares, pins, mobility, warnings and errors) stays with the driver;
here X lives in textures, a gradient is the texture `g`, sums come back as one float pair per
work group (the last level runs in float64 here) and the transposed product as N floats.
"""
import numpy as np

try:
    from ..vpffd_addon import solve as _vsolve
    from ..vpffd_addon import steps as _vsteps
    from ..vpffd_addon.gpu_layout import gpu_layout
except ImportError:  # loaded outside the extension package (tests, benchmarks: `gpu_backend`)
    from vpffd_addon import solve as _vsolve
    from vpffd_addon import steps as _vsteps
    from vpffd_addon.gpu_layout import gpu_layout
from .gpu_device import (GPUUnavailable, check_context, dispatch, empty_texture, kernels, make_texture,
                         pad_to_vec4, read_texture)
from .gpu_shaders import GROUP, MAX_INDEX, TW

#: What the GPU's steps can do (`vpffd_addon.steps.CAPABILITIES` has the NumPy steps' list).
CAPABILITIES = frozenset({"plain_measure"})


def supports(options=None, binding=None):
    """(ok, reason): whether the GPU path implements these solve options (and this binding).

    options: a dict with any of axes, directions, pins, mobility, islands, preserve_volume.
    The GPU path does lattice-axis directions only (a string of distinct letters from "XYZ"),
    one volume row (islands off) and preserve_volume on; pins and mobility work (their rows and
    the closed forms are on the CPU side of the one solve driver)."""
    o = dict(options or {})
    if o.get("directions") is not None:
        return False, "the GPU path corrects along lattice axes only (world directions use the CPU)"
    if o.get("islands"):
        return False, "per-island volumes are solved on the CPU"
    if not o.get("preserve_volume", True):
        return False, "without volume preservation the CPU path is used"
    axes = o.get("axes", "XYZ")
    if not axes:
        return False, "no correction axes"
    try:
        _vsolve.parse_directions(axes, None)
    except ValueError as exc:
        return False, str(exc)
    if binding is not None:
        return _binding_fits(binding)
    return True, "supported"


def _binding_fits(b):
    """(ok, reason): whether the binding `b` is a lattice's and its arrays fit the textures."""
    if not hasattr(b, "weight_shape"):
        return False, "cages are solved on the CPU (the GPU path does Lattice objects)"
    n_blocks, Kw, Kuv = b.weight_shape           # (without making the weights: a CPU solve needs none)
    n_slots = b.x0.shape[1]
    sizes = {"weights": n_slots * Kuv, "one-ring": 3 * b.n_faces, "pieces": n_blocks * Kw * Kuv}
    for what, n in sizes.items():
        if n >= MAX_INDEX or -(-n // TW) > 16384:
            return False, f"the binding is too large for the GPU path ({what}: {n} entries)"
    if b.lattice.n_points >= MAX_INDEX:
        return False, "too many control points for the GPU path"
    return True, "supported"


class GPUSolver:
    """A lattice binding uploaded to the GPU once (its arrays from `vpffd_addon.gpu_layout`);
    `steps` hands `vpffd_addon.solve.solve` the per-slot work as compute-shader kernels, and
    `solve` runs that driver. Raises GPUUnavailable (no GPU context, no compute support, compile
    error, binding too large). Use it from Blender's main thread only; `free()` drops the GPU
    textures early. A binding that changes (a re-embedded frame) needs a new solver."""

    def __init__(self, binding):
        ok, why = _binding_fits(binding)
        if not ok:
            raise GPUUnavailable(why)
        check_context()
        b = self.binding = binding
        self.n_slots = b.x0.shape[1]
        self.n_blocks, self.Kw, self.bs = b.ww.shape
        self.Kuv = b.wuv.shape[1]
        self.N = b.lattice.n_points
        self.V = b.n_verts
        self.k = kernels(self.bs, self.Kw, self.Kuv)
        try:
            self._upload(gpu_layout(b))
        except GPUUnavailable:
            raise
        except Exception as exc:
            raise GPUUnavailable(f"uploading the binding to the GPU failed ({exc})") from None
        if len(b.island_origin) == 1:
            self.origins = b.island_origin[0][None]
        else:
            self.origins = b.origins(np.arange(self.V))
        self.disp = None

    def _upload(self, layout):
        tex = {name: make_texture(layout[name]) for name in
               ("wuv", "ww", "s", "block_run", "run_idx", "slot", "ring_start", "cp_start", "cp_piece")}
        tex["x0"] = make_texture(pad_to_vec4(layout["x0"]), 4)
        tex["ring"] = make_texture(layout["ring"], 2)
        self.n_pieces = len(layout["cp_piece"])
        # Work textures.
        tex["X"] = [empty_texture(self.n_slots) for _ in range(3)]
        tex["g"] = empty_texture(self.n_slots)
        tex["piece"] = empty_texture(self.n_pieces)
        tex["alpha"] = empty_texture(self.N)
        tex["partial_slots"] = empty_texture(-(-self.n_slots // GROUP), 4)
        tex["verts"] = empty_texture(self.V, 4)
        self.tex = tex
        self.nbytes = int(sum(t.width * t.height * (16 if t.format.startswith("RGBA") else
                                                    8 if t.format.startswith("RG") else 4)
                              for v in tex.values() for t in (v if isinstance(v, list) else [v])))

    def free(self):
        """Drop the GPU textures (the solver cannot be used afterwards)."""
        self.tex = None

    def _run(self, name, n, samplers=(), images=(), ints=(), floats=()):
        sh = self.k[name]
        for sname, t in samplers:
            sh.uniform_sampler(sname, t)
        for iname, t in images:
            sh.image(iname, t)
        for cname, v in ints:
            sh.uniform_int(cname, int(v))
        for cname, v in floats:
            sh.uniform_float(cname, float(v))
        return dispatch(sh, n)

    def steps(self, binding):
        """The per-slot steps of one solve on this solver's textures (`vpffd_addon.steps`)."""
        if binding is not self.binding:
            raise GPUUnavailable("the GPU solver was made for another binding")
        if self.tex is None:
            raise GPUUnavailable("the GPU solver was freed")
        return _GPUSteps(self)

    def solve(self, points, **options):
        """`vpffd_addon.solve.solve` of this solver's binding with the GPU's steps: the same
        options, closed forms, warnings and errors as the CPU path, for what the GPU does (lattice
        axes, one volume row, pins and mobility: `supports`). Raises ValueError for bad input and
        GPUUnavailable when the GPU fails (fall back to the CPU)."""
        ok, why = supports(options)
        if not ok:
            raise ValueError(why)
        check_context()
        try:
            return _vsolve.solve(self.binding, points, steps=_StepsOf(self), **options)
        except (ValueError, GPUUnavailable):
            raise
        except Exception as exc:
            raise GPUUnavailable(f"the GPU solve failed ({type(exc).__name__}: {exc})") from None


class _StepsOf:
    """The `steps` factory `vpffd_addon.solve.solve` takes, for one GPU solver."""

    def __init__(self, solver):
        self.solver = solver
        self.capabilities = _GPUSteps.capabilities

    def __call__(self, binding):
        return self.solver.steps(binding)


class _GPUSteps(_vsteps.Steps):
    """`vpffd_addon.steps.NumpySteps`'s interface on the GPU: X lives in textures, a gradient is
    the texture `g` (its handle a token), sums come back as a few hundred partial sums whose last
    level runs in float64 here, and the transposed product comes back as N floats. No directions
    other than the lattice axes, one volume row (`capabilities`)."""

    capabilities = CAPABILITIES
    backend = "GPU"
    float32 = True

    def __init__(self, solver):
        super().__init__()
        self.s = solver
        self.uploaded = None          # the D now in the `disp` texture
        self.g = None                 # token of the gradient now in the `g` texture
        self.g_axis = None
        self.sums = {}

    def _upload(self, D):
        if self.uploaded is None or not np.array_equal(self.uploaded, D):
            self.s.disp = make_texture(pad_to_vec4(np.asarray(D, np.float32)), 4)
            self.uploaded = np.array(D, copy=True)

    def _forward(self, components, D):
        self._upload(D)
        T = self.s.tex
        for c in components:
            self.s._run("forward", self.s.n_slots,
                        [("x0", T["x0"]), ("wuv", T["wuv"]), ("ww", T["ww"]), ("block_run", T["block_run"]),
                         ("run_idx", T["run_idx"]), ("disp", self.s.disp)],
                        [("x_out", T["X"][c])], [("n", self.s.n_slots), ("comp", c)])

    def _gradient(self, a1, a2):
        T = self.s.tex
        self.s._run("gradient", self.s.n_slots,
                    [("xp", T["X"][a1]), ("xq", T["X"][a2]), ("ring_start", T["ring_start"]),
                     ("ring", T["ring"])], [("g_out", T["g"])], [("n", self.s.n_slots)])
        self.g, self.g_axis, self.sums = object(), 3 - a1 - a2, {}
        return self.g

    def _check(self, g):
        if g is not self.g:
            raise GPUUnavailable("a gradient that is no longer on the GPU was asked for")

    def _slot_sums(self, axis, g):
        """(sum x0_axis * g, sum |s g|) over the slots, by the reduce kernel's partial sums."""
        self._check(g)
        if axis not in self.sums:
            T = self.s.tex
            groups = self.s._run("reduce_slots", self.s.n_slots,
                                 [("x0", T["x0"]), ("g", T["g"]), ("s", T["s"])],
                                 [("partial", T["partial_slots"])], [("n", self.s.n_slots), ("comp", axis)])
            sums = read_texture(T["partial_slots"], groups, 4)[:, :2].astype(np.float64).sum(0)
            self.sums[axis] = sums
        return self.sums[axis]

    def x0_dot(self, axis, g, rows, k=1):
        return np.array([self._slot_sums(axis, g)[0]])

    def flux(self, g, rows, k=1):
        return np.array([self._slot_sums(self.g_axis, g)[1]])

    def transpose(self, g, rows, k=1):
        self._check(g)
        T = self.s.tex
        self.s._run("pieces", self.s.n_pieces, [("wuv", T["wuv"]), ("ww", T["ww"]), ("g", T["g"])],
                    [("piece", T["piece"])], [("n", self.s.n_pieces)])
        self.s._run("alpha", self.s.N, [("cp_start", T["cp_start"]), ("cp_piece", T["cp_piece"]),
                                        ("piece", T["piece"])], [("alpha_out", T["alpha"])], [("n", self.s.N)])
        return read_texture(T["alpha"], self.s.N, 1)[:, 0].astype(np.float64)[None]

    def verts(self, D):
        self.refresh((0, 1, 2), D)
        T = self.s.tex
        self.s._run("gather", self.s.V, [("slot", T["slot"]), ("x_0", T["X"][0]), ("x_1", T["X"][1]),
                                         ("x_2", T["X"][2])], [("verts_out", T["verts"])], [("n", self.s.V)])
        # One pass: the float32 texels widen to float64 inside the addition (as astype would).
        out = np.empty((self.s.V, 3))
        np.add(read_texture(T["verts"], self.s.V, 4)[:, :3], self.s.origins, out=out)
        return out

    def finite(self, verts=None):
        # The slots' coordinates live on the GPU: what comes back (`verts`) is what is checked.
        return verts is None or bool(np.isfinite(verts).all())

    def direction_gradient(self, p, q, D):
        raise ValueError("the GPU path corrects along lattice axes only")

    def x_dot(self, e, axis, g, rows, k=1, D=None):
        """sum X_axis * g: the reduce kernel run on the X texture instead of x0's."""
        if axis is None:
            raise ValueError("the GPU path corrects along lattice axes only")
        self._check(g)
        self.refresh((axis,), D)
        T = self.s.tex
        groups = self.s._run("reduce_slots", self.s.n_slots,
                             [("x0", T["X"][axis]), ("g", T["g"]), ("s", T["s"])],
                             [("partial", T["partial_slots"])], [("n", self.s.n_slots), ("comp", 0)])
        return np.array([read_texture(T["partial_slots"], groups, 4)[:, 0].astype(np.float64).sum()])

    def add_along(self, e, t):
        raise ValueError("the GPU path corrects along lattice axes only")
