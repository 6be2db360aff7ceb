"""VP-FFD Blender extension: volume-preserving lattice deformation.

Only register/unregister live here. Nothing imports bpy at module level, so the repository root
imports without Blender (pytest collects it); the Blender-facing code is in `operators/` and the
numerical core, usable on its own, in `vpffd_addon/`.
"""


def register():
    from . import operators
    operators.register()


def unregister():
    from . import operators
    operators.unregister()
