"""Blender-facing code of the extension (operators, properties, panels, handlers, mesh I/O).

The core it drives is `vpffd_addon`; the bind/unbind/apply operators, the panel and the frame
handlers are the next milestone, so for now the extension registers no classes.
"""
import bpy

classes = ()

register, unregister = bpy.utils.register_classes_factory(classes)
