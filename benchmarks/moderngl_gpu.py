"""The part of Blender's `gpu` module that the GPU path calls (`operators/gpu_device.py`), on
moderngl (OpenGL 4.3 through EGL, no window), so that the extension's own kernels and solve driver
run, unchanged, on a machine where Blender cannot: a GPU server with no display and no room for
the bpy wheel.

Only a benchmark uses it (`benchmarks/gpu_benchmark.py --standalone`): it times the GPU path on real
hardware. What Blender adds around the kernels (its own GPU context, the draw loop) is not in it.

`install()` puts the module into `sys.modules["gpu"]` before the backend is loaded. Each call
mirrors Blender's (GLSL generated from a `GPUShaderCreateInfo` as Blender's OpenGL backend does:
samplers and images on the numbered slots, push constants as uniforms); after every dispatch a
memory barrier makes the images written visible to the next kernel's texel fetches.
"""
import sys
import types

import numpy as np

_CHANNELS = {"R32F": 1, "RG32F": 2, "RGBA32F": 4}
_IMAGE_FORMAT = {"R32F": "r32f", "RG32F": "rg32f", "RGBA32F": "rgba32f"}
_ctx = None


def context():
    """The one moderngl context (EGL, OpenGL 4.3 or newer), made on first use."""
    global _ctx
    if _ctx is None:
        import moderngl
        _ctx = moderngl.create_context(standalone=True, backend="egl", require=430)
    return _ctx


class Buffer(bytearray):
    """`gpu.types.Buffer` of FLOATs: bytes that NumPy reads with `np.frombuffer`."""

    def __init__(self, kind="FLOAT", size=0, data=None):
        if kind != "FLOAT":
            raise TypeError("only FLOAT buffers are used")
        if data is None:
            super().__init__(4 * int(size))
        elif isinstance(data, (bytes, bytearray)):
            super().__init__(data)
        else:
            super().__init__(np.ascontiguousarray(data, np.float32).reshape(-1).tobytes())
        self.dimensions = len(self) // 4


class GPUTexture:
    def __init__(self, size, format="RGBA8", data=None):
        if format not in _CHANNELS:
            raise ValueError(f"texture format {format} is not used by the backend")
        self.width, self.height = int(size[0]), int(size[1])
        self.format = format
        self.tex = context().texture((self.width, self.height), _CHANNELS[format],
                                     data=None if data is None else bytes(data), dtype="f4")

    def read(self):
        return Buffer("FLOAT", data=self.tex.read())


class GPUShaderCreateInfo:
    def __init__(self):
        self.samplers, self.images, self.consts, self.local, self.source = [], [], [], (1, 1, 1), ""
        self.defines, self.typedefs = [], []

    def sampler(self, slot, kind, name):
        self.samplers.append((slot, name))

    def image(self, slot, fmt, kind, name, qualifiers=frozenset()):
        self.images.append((slot, fmt, name, frozenset(qualifiers)))

    def push_constant(self, kind, name):
        self.consts.append(({"INT": "int", "FLOAT": "float"}[kind], name))

    def local_group_size(self, x, y=1, z=1):
        self.local = (x, y, z)

    def define(self, name, value=""):
        self.defines.append((name, value))

    def typedef_source(self, source):
        self.typedefs.append(source)

    def compute_source(self, source):
        self.source = source


class GPUShader:
    def __init__(self, info):
        # Blender's order: defines, resources, the typedef source, then the compute source.
        lines = ["#version 430"] + [f"#define {name} {value}" for name, value in info.defines]
        lines.append("layout(local_size_x = %d, local_size_y = %d, local_size_z = %d) in;" % info.local)
        for slot, name in info.samplers:
            lines.append(f"layout(binding = {slot}) uniform sampler2D {name};")
        for slot, fmt, name, quals in info.images:
            access = ("writeonly " if quals == {"WRITE"} else "readonly " if quals == {"READ"} else "")
            lines.append(f"layout(binding = {slot}, {_IMAGE_FORMAT[fmt]}) uniform {access}image2D {name};")
        for kind, name in info.consts:
            lines.append(f"uniform {kind} {name};")
        lines.extend(info.typedefs)
        self.program = context().compute_shader("\n".join(lines) + "\n" + info.source)
        self.sampler_slot = {name: slot for slot, name in info.samplers}
        self.image_slot = {name: (slot, quals) for slot, _, name, quals in info.images}
        self.bound = {}

    def uniform_sampler(self, name, tex):
        self.bound[name] = tex

    def image(self, name, tex):
        self.bound[name] = tex

    def _set(self, name, value):
        if name in self.program:       # the GLSL compiler drops uniforms a kernel does not use
            self.program[name].value = value

    uniform_int = _set
    uniform_float = _set

    def dispatch(self, x, y, z):
        for name, tex in self.bound.items():
            if name in self.sampler_slot:
                tex.tex.use(location=self.sampler_slot[name])
            else:
                slot, quals = self.image_slot[name]
                tex.tex.bind_to_image(slot, read="READ" in quals, write="WRITE" in quals)
        self.program.run(x, y, z)
        context().memory_barrier()


def _create_from_info(info):
    return GPUShader(info)


def _dispatch(shader, x, y, z):
    shader.dispatch(x, y, z)


def module():
    """A module object with the attributes of Blender's `gpu` that the backend calls."""
    gpu = types.ModuleType("gpu")
    gpu.types = types.SimpleNamespace(Buffer=Buffer, GPUTexture=GPUTexture,
                                      GPUShaderCreateInfo=GPUShaderCreateInfo)
    gpu.shader = types.SimpleNamespace(create_from_info=_create_from_info)
    gpu.compute = types.SimpleNamespace(dispatch=_dispatch)
    gpu.platform = types.SimpleNamespace(
        renderer_get=lambda: context().info["GL_RENDERER"],
        version_get=lambda: context().info["GL_VERSION"],
        vendor_get=lambda: context().info["GL_VENDOR"])
    gpu.capabilities = types.SimpleNamespace(compute_shader_support_get=lambda: True)
    gpu._standalone_context = context      # lets the benchmark wait for each kernel
    return gpu


def install():
    """Make `import gpu` give this module (refuses inside Blender, which has the real one; and an
    `import bpy` afterwards puts Blender's back, so a standalone run never imports bpy)."""
    if "bpy" in sys.modules:
        raise RuntimeError("Blender's own gpu module is there: the standalone one is for machines without it")
    sys.modules["gpu"] = module()
    return sys.modules["gpu"]
