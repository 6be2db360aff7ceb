"""The GPU path's calls of Blender's `gpu` module: whether a GPU context with compute shaders is
here, the kernels compiled from `gpu_shaders` (cached per block size and tap counts), textures made,
read back and dispatched over. `gpu` is imported lazily, never at import or register time.

Read-back: ``np.array(tex.read())`` and ``np.asarray(memoryview(buf))`` give WRONG values in Blender
4.2-5.0; `read_texture` flattens the buffer first, which is right and zero-copy.
"""
import threading
import warnings

import numpy as np

from .gpu_shaders import GROUP, HEADER, KERNELS, SHARED, TW, TW_LOG


class GPUUnavailable(RuntimeError):
    """The GPU path cannot run here (the message says why); the caller falls back to the CPU."""


def gpu_module():
    """Blender's `gpu` module. Raises GPUUnavailable where it cannot be imported."""
    try:
        import gpu  # noqa: F401  (lazy: never at import or register time)
    except Exception as exc:  # pragma: no cover - bpy without gpu
        raise GPUUnavailable(f"the gpu module cannot be imported ({exc})") from None
    return gpu


def check_context():
    """Raise GPUUnavailable unless GPU calls work in this thread now; the `gpu` module."""
    if threading.current_thread() is not threading.main_thread():
        raise GPUUnavailable("GPU calls are only made from Blender's main thread")
    gpu = gpu_module()
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


# ------------------------------------------------------------------------------------------------
# Kernels

#: {(block size, Kw, Kuv): {kernel name: GPUShader}}, filled by `kernels`, emptied by `release`.
kernel_cache = {}


def kernels(bs, kw, kuv):
    """The compiled kernels ({name: GPUShader}, `gpu_shaders.KERNELS`) for a block size and tap
    counts (cached). Raises GPUUnavailable."""
    key = (bs, kw, kuv)
    if key in kernel_cache:
        return kernel_cache[key]
    gpu = gpu_module()
    defines = {"TW": TW, "TW_LOG": TW_LOG, "GROUP": GROUP, "BS": bs, "KW": kw, "KUV": kuv}
    out = {}
    for name, (samplers, images, consts, body) in KERNELS.items():
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
            for define, value in defines.items():    # not `key`: that names the cache entry
                info.define(define, str(value))
            if name in SHARED:
                info.typedef_source(SHARED[name])
            info.compute_source(HEADER + body)
            out[name] = gpu.shader.create_from_info(info)
        except Exception as exc:
            raise GPUUnavailable(f"the GPU kernel '{name}' did not compile ({exc})") from None
    kernel_cache[key] = out
    return out


def release():
    """Drop the compiled kernels (call from unregister, on the main thread). Never raises."""
    kernel_cache.clear()


# ------------------------------------------------------------------------------------------------
# Textures and dispatch


def _rows(n):
    return max(1, -(-int(n) // TW))


def make_texture(values, channels=1):
    """A TW-wide float texture holding `values` (n,) or (n, channels) row-major, zero-padded."""
    gpu = gpu_module()
    a = np.asarray(values, dtype=np.float32).reshape(-1, channels)
    h = _rows(len(a))
    data = np.zeros((h * TW, channels), np.float32)
    data[:len(a)] = a
    fmt = {1: "R32F", 2: "RG32F", 4: "RGBA32F"}[channels]
    buf = gpu.types.Buffer("FLOAT", data.size, data.ravel())
    return gpu.types.GPUTexture((TW, h), format=fmt, data=buf)


def empty_texture(n, channels=1):
    """A TW-wide float texture with room for n texels of `channels` (1, 2 or 4) floats."""
    gpu = gpu_module()
    fmt = {1: "R32F", 2: "RG32F", 4: "RGBA32F"}[channels]
    return gpu.types.GPUTexture((TW, _rows(n)), format=fmt)


def read_texture(tex, n, channels):
    """The first n texels of a float texture as a (n, channels) float32 array, without Python loops.

    `np.array(tex.read())` is WRONG in Blender 4.2-5.0; flattening the Buffer's dimensions first
    and viewing it with np.frombuffer is right (and zero-copy)."""
    buf = tex.read()
    buf.dimensions = tex.width * tex.height * channels
    return np.frombuffer(buf, np.float32).reshape(-1, channels)[:n]


def dispatch(shader, n):
    """Run `shader` over n invocations (work groups of GROUP, at most 4096 a row): the number of
    work groups."""
    gpu = gpu_module()
    groups = max(1, -(-int(n) // GROUP))
    gx = min(groups, 4096)
    gpu.compute.dispatch(shader, gx, -(-groups // gx), 1)
    return groups


def pad_to_vec4(a):
    """(n, c) values, c <= 4 -> (n, 4) float32, zero-padded (one RGBA32F texel each)."""
    out = np.zeros((len(a), 4), np.float32)
    out[:, :a.shape[1]] = a
    return out
