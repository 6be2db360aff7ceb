"""GPU path of the volume-preserving solve: Blender's `gpu` compute shaders (docs/design.md, "The
GPU dispatch plan").

Kernels and buffers only: the solve itself (closed forms, shares, pins, mobility, warnings and
errors) is `vpffd_addon.solve.solve`, the one driver, which asks a steps object for the per-slot
work (`vpffd_addon.steps`); here that object runs compute shaders on textures uploaded once per
binding. The arrays uploaded are built and tested in the core (`vpffd_addon.gpu_layout`).
What stays on the CPU and why: directions other than the lattice axes (their gradient needs the
projected coordinates of every slot), per-island rows (one transposed product per island), cages
(no fixed blocks of control points). `gpu` is imported lazily, never at import or register time.

Textures are 4096 texels wide, row-major; integers are stored exactly as floats < 2**24, because
Python's `GPUTexture` only accepts FLOAT data. Kernels (local size 256, no atomics anywhere,
every sum in a fixed order):

- ``forward``: X_c = x0_c + S B D_c for one component c (the standard FFD), slot-parallel;
- ``gradient``: g = dV/dx_e per slot, a gather over the slot's incident faces (one-ring CSR) of the
  per-face terms ``(p_m q_n - q_m p_n) / 6``;
- ``reduce_slots``: per work group, tree sums of ``x0_e * g`` and ``|g s|`` (volume and flux terms);
- ``pieces``: per (block, tap) the dot product of the block's weights with g (64 slots at most);
- ``alpha``: per control point, the sum of its pieces in CSR order (the transposed product);
- ``gather``: the final coordinates per vertex, ``X[slot[v]]``, one RGBA32F read-back.

What crosses the bus per direction: up, the N control-point offsets when they changed (one RGBA32F
texture); down, one float pair per 256 slots (the last level of the tree sums runs in float64 on
the CPU) and the N values of the transposed product; at the end the final coordinates (V x 4
floats).

Read-back: ``np.array(tex.read())`` and ``np.asarray(memoryview(buf))`` give WRONG values in Blender
4.2-5.0; `read_texture` flattens the buffer first, which is right and zero-copy.
"""
import threading
import warnings

import numpy as np

try:
    from ..vpffd_addon import backends as _vbackends
    from ..vpffd_addon import solve as _vsolve
    from ..vpffd_addon import steps as _vsteps
    from ..vpffd_addon.gpu_layout import gpu_layout
except ImportError:  # loaded outside the extension package (tests, benchmarks)
    from vpffd_addon import backends as _vbackends
    from vpffd_addon import solve as _vsolve
    from vpffd_addon import steps as _vsteps
    from vpffd_addon.gpu_layout import gpu_layout

#: Texture width (texels); indices map to (i % TW, i // TW).
TW = 4096
TW_LOG = 12
#: Work-group size of every kernel.
GROUP = 256
#: Integers travel as floats: exact below 2**24.
MAX_INDEX = 1 << 24
#: Auto uses the GPU from this many vertices on (below, uploads and dispatch overhead dominate).
AUTO_MIN_VERTS = 50000
#: Renderers on which the GPU path is slower than NumPy (software rasterisers).
SOFTWARE_RENDERERS = ("llvmpipe", "softpipe", "swiftshader", "software rasterizer", "lavapipe")


class GPUUnavailable(RuntimeError):
    """The GPU path cannot run here (the message says why); the caller falls back to the CPU."""


# ------------------------------------------------------------------------------------------------
# Availability and backend choice


def _gpu():
    try:
        import gpu  # noqa: F401  (lazy: never at import or register time)
    except Exception as exc:  # pragma: no cover - bpy without gpu
        raise GPUUnavailable(f"the gpu module cannot be imported ({exc})") from None
    return gpu


def _check_context():
    """Raise GPUUnavailable unless GPU calls work in this thread now."""
    if threading.current_thread() is not threading.main_thread():
        raise GPUUnavailable("GPU calls are only made from Blender's main thread")
    gpu = _gpu()
    try:
        gpu.types.GPUTexture((1, 1), format="R32F")
    except Exception as exc:
        raise GPUUnavailable(f"no GPU context ({exc})") from None
    support = getattr(gpu.capabilities, "compute_shader_support_get", None)
    try:
        with warnings.catch_warnings():  # deprecated (always true) from 4.x on
            warnings.simplefilter("ignore")
            has_compute = support is None or support()
        if not has_compute:
            raise GPUUnavailable("this GPU has no compute-shader support")
    except GPUUnavailable:
        raise
    except Exception:
        pass
    if not hasattr(gpu, "compute") or not hasattr(gpu.types, "GPUShaderCreateInfo"):
        raise GPUUnavailable("this Blender has no Python compute shaders (needs 4.2 or newer)")
    return gpu


def available():
    """(ok, reason): whether the GPU path can run here now. Never raises.

    Fails in background mode before a GPU backend exists ("GPU functions for drawing are not
    available in background mode"), without compute support, off the main thread, or when the
    kernels do not compile; the reason says which."""
    try:
        _check_context()
        _kernels(64, 4, 16)
        return True, "GPU compute shaders are available (" + renderer() + ")"
    except GPUUnavailable as exc:
        return False, str(exc)
    except Exception as exc:  # never raise from here
        return False, f"GPU check failed: {type(exc).__name__}: {exc}"


def renderer():
    """The GPU renderer's name, or '' when unknown. Never raises."""
    try:
        return str(_gpu().platform.renderer_get())
    except Exception:
        return ""


def is_software_renderer():
    """True on software OpenGL (Mesa llvmpipe and the like), where the GPU path is slow."""
    name = renderer().lower()
    return any(s in name for s in SOFTWARE_RENDERERS)


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
# Kernels

# Constants reach the kernels as the create-info's defines, so that the shared-memory declarations
# (below) see them too: Blender 5.1 and newer drop a `shared` declaration written in the compute
# source, and a `#define` in that source is not visible to the typedef source that replaces it.
_HEADER = """
#define AT(i) ivec2((i) & (TW - 1), (i) >> TW_LOG)
#define FETCH(t, i) texelFetch(t, AT(i), 0)
#define IFETCH(t, i) int(texelFetch(t, AT(i), 0).r)
int group_index() { return int(gl_WorkGroupID.y * gl_NumWorkGroups.x + gl_WorkGroupID.x); }
int global_index() { return group_index() * GROUP + int(gl_LocalInvocationID.x); }
"""

# Each kernel: (samplers, images, push constants, body). Sampler/image slots are numbered
# distinctly within a kernel.
# End of the reduction kernel: a tree sum of each work group's vec2 `v` in shared memory (`acc`,
# declared in _SHARED), written by the group's first invocation as one texel of `partial`.
_GROUP_SUM_TAIL = """
  acc[t] = v;
  barrier();
  for (uint h = GROUP / 2u; h > 0u; h >>= 1) {
    if (t < h) acc[t] += acc[t + h];
    barrier();
  }
  if (t == 0u) imageStore(partial, AT(group_index()), vec4(acc[0], 0.0, 0.0));
}"""

_KERNELS = {
    "forward": (
        ("x0", "wuv", "ww", "block_run", "run_idx", "disp"), (("x_out", "R32F", "WRITE"),),
        (("INT", "n"), ("INT", "comp")), """
void main() {
  int i = global_index();
  if (i >= n) return;
  int run = IFETCH(block_run, i / BS);
  int base = run * KW * KUV;
  float acc = 0.0;
  for (int kw = 0; kw < KW; kw++) {
    float inner = 0.0;
    for (int k = 0; k < KUV; k++) {
      int p = IFETCH(run_idx, base + kw * KUV + k);
      inner += FETCH(wuv, i * KUV + k).r * FETCH(disp, p)[comp];
    }
    acc += FETCH(ww, i * KW + kw).r * inner;
  }
  imageStore(x_out, AT(i), vec4(FETCH(x0, i)[comp] + acc));
}"""),
    "gradient": (
        ("xp", "xq", "ring_start", "ring"), (("g_out", "R32F", "WRITE"),), (("INT", "n"),), """
void main() {
  int i = global_index();
  if (i >= n) return;
  int e0 = IFETCH(ring_start, i), e1 = IFETCH(ring_start, i + 1);
  float g = 0.0;
  for (int e = e0; e < e1; e++) {
    vec4 mn = FETCH(ring, e);
    int m = int(mn.r), k = int(mn.g);
    g += FETCH(xp, m).r * FETCH(xq, k).r - FETCH(xq, m).r * FETCH(xp, k).r;
  }
  imageStore(g_out, AT(i), vec4(g * (1.0 / 6.0)));
}"""),
    "reduce_slots": (
        ("x0", "g", "s"), (("partial", "RGBA32F", "WRITE"),), (("INT", "n"), ("INT", "comp")), """
void main() {
  int i = global_index();
  uint t = gl_LocalInvocationID.x;
  vec2 v = vec2(0.0);
  if (i < n) {
    float gv = FETCH(g, i).r;
    v = vec2(FETCH(x0, i)[comp] * gv, abs(gv * FETCH(s, i).r));
  }
""" + _GROUP_SUM_TAIL),
    "pieces": (
        ("wuv", "ww", "g"), (("piece", "R32F", "WRITE"),), (("INT", "n"),), """
void main() {
  int i = global_index();
  if (i >= n) return;
  int blk = i / (KW * KUV), e = i % (KW * KUV);
  int kw = e / KUV, k = e % KUV;
  float acc = 0.0;
  for (int p = 0; p < BS; p++) {
    int slot = blk * BS + p;
    acc += FETCH(ww, slot * KW + kw).r * FETCH(wuv, slot * KUV + k).r * FETCH(g, slot).r;
  }
  imageStore(piece, AT(i), vec4(acc));
}"""),
    "alpha": (
        ("cp_start", "cp_piece", "piece"), (("alpha_out", "R32F", "WRITE"),), (("INT", "n"),), """
void main() {
  int i = global_index();
  if (i >= n) return;
  int j0 = IFETCH(cp_start, i), j1 = IFETCH(cp_start, i + 1);
  float acc = 0.0;
  for (int j = j0; j < j1; j++) acc += FETCH(piece, IFETCH(cp_piece, j)).r;
  imageStore(alpha_out, AT(i), vec4(acc));
}"""),
    "gather": (
        ("slot", "x_0", "x_1", "x_2"), (("verts_out", "RGBA32F", "WRITE"),), (("INT", "n"),), """
void main() {
  int i = global_index();
  if (i >= n) return;
  int s = IFETCH(slot, i);
  imageStore(verts_out, AT(i), vec4(FETCH(x_0, s).r, FETCH(x_1, s).r, FETCH(x_2, s).r, 0.0));
}"""),
}

#: Work-group shared memory of each kernel that has any (given through the create-info).
_SHARED = {"reduce_slots": "shared vec2 acc[GROUP];\n"}

_kernel_cache = {}


def _kernels(bs, kw, kuv):
    """The compiled kernels for a block size and tap counts (cached). Raises GPUUnavailable."""
    key = (bs, kw, kuv)
    if key in _kernel_cache:
        return _kernel_cache[key]
    gpu = _gpu()
    defines = {"TW": TW, "TW_LOG": TW_LOG, "GROUP": GROUP, "BS": bs, "KW": kw, "KUV": kuv}
    out = {}
    for name, (samplers, images, consts, body) in _KERNELS.items():
        try:
            info = gpu.types.GPUShaderCreateInfo()
            slot = 0
            for s in samplers:
                info.sampler(slot, "FLOAT_2D", s)
                slot += 1
            for img, fmt, access in images:
                quals = {"READ", "WRITE"} if access == "READ_WRITE" else {access}
                info.image(slot, fmt, "FLOAT_2D", img, qualifiers=quals)
                slot += 1
            for typ, cname in consts:
                info.push_constant(typ, cname)
            info.local_group_size(GROUP, 1, 1)
            for key, value in defines.items():
                info.define(key, str(value))
            if name in _SHARED:
                info.typedef_source(_SHARED[name])
            info.compute_source(_HEADER + body)
            out[name] = gpu.shader.create_from_info(info)
        except Exception as exc:
            raise GPUUnavailable(f"the GPU kernel '{name}' did not compile ({exc})") from None
    _kernel_cache[key] = out
    return out


def release():
    """Drop the compiled kernels (call from unregister, on the main thread). Never raises."""
    _kernel_cache.clear()


def _accepts(preference, binding, options, fresh=False):
    """The GPU entry's own rules (`choose`: the options and sizes it supports, Auto's)."""
    return choose(preference, binding.n_verts, options, binding, fresh)


def register():
    """Register the GPU path in the core's registry of backends (`vpffd_addon/backends.py`):
    lattice bindings, lattice axes, one volume row; it makes its solver per binding
    (`GPUSolver`), so it lends no steps to the CPU's solve."""
    _vbackends.register(_vbackends.Backend(
        "GPU", "GPU", "GPU", frozenset({"lattice"}) | _GPUSteps.capabilities,
        available=available, accepts=_accepts))


def unregister():
    """Take the GPU path out of the registry and drop its kernels (on the main thread)."""
    _vbackends.unregister("GPU")
    release()


# ------------------------------------------------------------------------------------------------
# Textures


def _rows(n):
    return max(1, -(-int(n) // TW))


def make_texture(values, channels=1):
    """A TW-wide float texture holding `values` (n,) or (n, channels) row-major, zero-padded."""
    gpu = _gpu()
    a = np.asarray(values, dtype=np.float32).reshape(-1, channels)
    h = _rows(len(a))
    data = np.zeros((h * TW, channels), np.float32)
    data[:len(a)] = a
    fmt = {1: "R32F", 2: "RG32F", 4: "RGBA32F"}[channels]
    buf = gpu.types.Buffer("FLOAT", data.size, data.ravel())
    return gpu.types.GPUTexture((TW, h), format=fmt, data=buf)


def empty_texture(n, channels=1):
    gpu = _gpu()
    fmt = {1: "R32F", 2: "RG32F", 4: "RGBA32F"}[channels]
    return gpu.types.GPUTexture((TW, _rows(n)), format=fmt)


def read_texture(tex, n, channels):
    """The first n texels of a float texture as a (n, channels) float32 array, without Python loops.

    `np.array(tex.read())` is WRONG in Blender 4.2-5.0; flattening the Buffer's dimensions first
    and viewing it with np.frombuffer is right (and zero-copy)."""
    buf = tex.read()
    buf.dimensions = tex.width * tex.height * channels
    return np.frombuffer(buf, np.float32).reshape(-1, channels)[:n]


def _dispatch(shader, n):
    gpu = _gpu()
    groups = max(1, -(-int(n) // GROUP))
    gx = min(groups, 4096)
    gpu.compute.dispatch(shader, gx, -(-groups // gx), 1)
    return groups


def _pad_to_vec4(a):
    out = np.zeros((len(a), 4), np.float32)
    out[:, :a.shape[1]] = a
    return out


# ------------------------------------------------------------------------------------------------
# Solver


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
        _check_context()
        b = self.binding = binding
        self.n_slots = b.x0.shape[1]
        self.n_blocks, self.Kw, self.bs = b.ww.shape
        self.Kuv = b.wuv.shape[1]
        self.N = b.lattice.n_points
        self.V = b.n_verts
        self.k = _kernels(self.bs, self.Kw, self.Kuv)
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
        tex["x0"] = make_texture(_pad_to_vec4(layout["x0"]), 4)
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
        return _dispatch(sh, n)

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
        _check_context()
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

    capabilities = frozenset({"plain_measure"})
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
            self.s.disp = make_texture(_pad_to_vec4(np.asarray(D, np.float32)), 4)
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

    def finite(self):
        return True       # the coordinates are checked where they come back (`verts`)

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
