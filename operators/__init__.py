"""Blender-facing code of the extension: settings, operators, panel, handlers, mesh I/O.

The numerical work is done by `vpffd_addon`; this package reads Blender data into flat arrays,
calls it, and writes the result as offsets that the VP-FFD Geometry Nodes modifier applies.
"""
import bpy

from . import (bake_ops, cage, compiled_backend, demos, fit, gpu_backend, handlers, log, ops, overlay,
               panel, properties)

classes = (properties.classes + ops.classes + bake_ops.classes + panel.classes + demos.classes
           + cage.classes + fit.classes)

_register_classes, _unregister_classes = bpy.utils.register_classes_factory(classes)


def register():
    log.install()
    _register_classes()
    properties.register()
    ops.register()
    gpu_backend.register()
    handlers.register()
    demos.register()
    cage.register()
    fit.register()
    overlay.register()


def unregister():
    compiled_backend.unregister()
    gpu_backend.unregister()
    overlay.unregister()
    fit.unregister()
    cage.unregister()
    demos.unregister()
    handlers.unregister()
    ops.unregister()
    properties.unregister()
    _unregister_classes()
    log.uninstall()
