"""The GPU path's compute-shader sources (GLSL) and the texture layout they assume; pure text,
compiled by `gpu_device.kernels` (docs/design.md, "The GPU dispatch plan").

Textures are `TW` texels wide, row-major; integers are stored exactly as floats < `MAX_INDEX`
(2**24), because Python's `GPUTexture` only accepts FLOAT data. Kernels (local size `GROUP`, no
atomics anywhere, every sum in a fixed order):

- ``forward``: X_c = x0_c + S B D_c for one component c (the standard FFD), slot-parallel;
- ``gradient``: g = dV/dx_e per slot, a gather over the slot's incident faces (one-ring CSR) of the
  per-face terms ``(p_m q_n - q_m p_n) / 6``;
- ``reduce_slots``: per work group, tree sums of ``x0_e * g`` and ``|g s|`` (volume and flux terms);
- ``pieces``: per (block, tap) the dot product of the block's weights with g (64 slots at most);
- ``alpha``: per control point, the sum of its pieces in CSR order (the transposed product);
- ``gather``: the final coordinates per vertex, ``X[slot[v]]``, one RGBA32F read-back.
"""

#: Texture width (texels); indices map to (i % TW, i // TW).
TW = 4096
TW_LOG = 12
#: Work-group size of every kernel.
GROUP = 256
#: Integers travel as floats: exact below 2**24.
MAX_INDEX = 1 << 24

# Constants reach the kernels as the create-info's defines, so that the shared-memory declarations
# (`SHARED`) see them too: Blender 5.1 and newer drop a `shared` declaration written in the compute
# source, and a `#define` in that source is not visible to the typedef source that replaces it.
#: What every kernel's compute source starts with.
HEADER = """
#define AT(i) ivec2((i) & (TW - 1), (i) >> TW_LOG)
#define FETCH(t, i) texelFetch(t, AT(i), 0)
#define IFETCH(t, i) int(texelFetch(t, AT(i), 0).r)
int group_index() { return int(gl_WorkGroupID.y * gl_NumWorkGroups.x + gl_WorkGroupID.x); }
int global_index() { return group_index() * GROUP + int(gl_LocalInvocationID.x); }
"""

# End of the reduction kernel: a tree sum of each work group's vec2 `v` in shared memory (`acc`,
# declared in SHARED), written by the group's first invocation as one texel of `partial`.
_GROUP_SUM_TAIL = """
  acc[t] = v;
  barrier();
  for (uint h = GROUP / 2u; h > 0u; h >>= 1) {
    if (t < h) acc[t] += acc[t + h];
    barrier();
  }
  if (t == 0u) imageStore(partial, AT(group_index()), vec4(acc[0], 0.0, 0.0));
}"""

#: Each kernel: (samplers, images (name, format, access), push constants (type, name), body).
#: Sampler/image slots are numbered distinctly within a kernel.
KERNELS = {
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
SHARED = {"reduce_slots": "shared vec2 acc[GROUP];\n"}
