"""The bake's operators (Bake to Point Cache, Use Cache, Use Live) and the Bake sub-panel."""
import logging
import os
import time

import bpy
from bpy.props import BoolProperty, EnumProperty, IntProperty, StringProperty

from . import deformers, modifier
from .bake import Baker
from .bake_files import FORMAT_ITEMS, FORMATS, BakeError, default_filepath
from .cache_modifier import find_cache, using_cache
from .cache_switch import switch_to_cache, switch_to_live
from .text import report

log = logging.getLogger(__name__)


# Path properties that accept '//' without a warning (the option is in 5.0, not in 4.2).
_PATH_OPTIONS = ({"SKIP_SAVE", "PATH_SUPPORTS_BLEND_RELATIVE"}
                 if "is_path_supports_blend_relative" in bpy.types.Property.bl_rna.properties
                 else {"SKIP_SAVE"})


# Frames baked per timer event: as many as fit in this time (at least one). The window redraws
# after each event, so a short budget ties the bake's speed to redrawing the viewport.
_MODAL_BUDGET_S = 0.5


def _format_changed(self, _context):
    """Keep the file name's extension in step with the chosen format."""
    root, ext = os.path.splitext(self.filepath)
    new = FORMATS[self.format]
    if ext.lower() in FORMATS.values() and ext.lower() != new:
        self.filepath = root + new


def _bound_mesh(context):
    ob = context.object
    return ob is not None and ob.type == "MESH" and deformers.is_bound(ob)


class OBJECT_OT_vpffd_bake(bpy.types.Operator):
    """Bake the volume-preserved deformation of a frame range to a point cache (PC2 or MDD) that
    Blender's Mesh Cache modifier plays without this extension"""
    bl_idname = "object.vpffd_bake"
    bl_label = "Bake to Point Cache"
    bl_options = {"REGISTER"}  # no redo panel: changing a setting must not silently re-bake
    _baker = None
    _timer = None

    filepath: StringProperty(
        name="File", subtype="FILE_PATH", default="", options=_PATH_OPTIONS,
        description="Cache file to write; empty: vpffd_<object>.pc2 next to the .blend file (in the "
                    "temporary folder while the file is not saved)")
    format: EnumProperty(
        name="Format", items=FORMAT_ITEMS, default="PC2", update=_format_changed,
        description="Point cache format (both are read by Blender's Mesh Cache modifier)")
    frame_start: IntProperty(
        name="Start", options={"SKIP_SAVE"},
        description="First frame to bake (default: the scene's start frame)")
    frame_end: IntProperty(
        name="End", options={"SKIP_SAVE"},
        description="Last frame to bake (default: the scene's end frame)")
    use_switch: BoolProperty(
        name="Switch to Cache", default=True,
        description="Afterwards, play the cache through a Mesh Cache modifier and disable the "
                    "VP-FFD modifier (switch back any time)")
    make_folder: BoolProperty(
        name="Create Folder", default=False, options={"SKIP_SAVE"},
        description="Create the file's folder if it does not exist (that one folder only)")

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return _bound_mesh(context)

    def _fill_defaults(self, context):
        scene = context.scene
        if not self.filepath:
            self.filepath = default_filepath(context.object, self.format)
        if not self.properties.is_property_set("frame_start"):
            self.frame_start = scene.frame_start
        if not self.properties.is_property_set("frame_end"):
            self.frame_end = scene.frame_end

    def invoke(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        self._fill_defaults(context)
        return context.window_manager.invoke_props_dialog(self, width=420)

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        layout.use_property_split = True
        layout.prop(self, "filepath")
        if not bpy.data.filepath:
            col = layout.column(align=True)
            if self.filepath.startswith("//"):
                texts = ("The .blend file is not saved: a path starting with // has no folder.",
                         "Save the file first, or choose a folder.")
            else:
                texts = ("The .blend file is not saved: the cache goes to the temporary folder.",
                         "Save the file first to keep the cache next to it.")
            for k, text in enumerate(texts):
                col.label(text=text, icon="INFO" if k == 0 else "BLANK1")
        layout.prop(self, "make_folder")
        layout.prop(self, "format")
        col = layout.column(align=True)
        col.prop(self, "frame_start")
        col.prop(self, "frame_end")
        layout.prop(self, "use_switch")

    def execute(self, context: bpy.types.Context) -> set[str]:
        self._fill_defaults(context)
        try:
            baker = Baker(context.object, context.scene, self.filepath, self.frame_start,
                          self.frame_end, self.format, self.make_folder)
            baker.start()
        except BakeError as exc:
            report(self, "ERROR", str(exc))
            return {"CANCELLED"}
        self._baker = baker
        if bpy.app.background or context.window is None:
            return self._run_blocking()
        wm = context.window_manager
        wm.progress_begin(0, baker.total)
        self._timer = wm.event_timer_add(0.001, window=context.window)
        wm.modal_handler_add(self)
        self._status(context)
        return {"RUNNING_MODAL"}

    def _run_blocking(self):
        baker = self._baker
        step = max(1, baker.total // 10)
        try:
            while not baker.step():
                if baker.done % step == 0:
                    log.info("baked %d/%d frames", baker.done, baker.total)
        except BakeError as exc:
            baker.abort()
            report(self, "ERROR", str(exc))
            return {"CANCELLED"}
        except BaseException:
            baker.abort()
            raise
        return self._finish()

    def _finish(self):
        try:
            result = self._baker.finish()
            if self.use_switch:
                switch_to_cache(self._baker.obj, self.filepath, result.format, result.frame_start,
                                self._baker.scene)
        except BakeError as exc:
            report(self, "ERROR", str(exc))
            return {"CANCELLED"}
        report(self, "INFO", f"baked frames {result.frame_start}-{result.frame_end} "
                              f"({result.n_verts:,} vertices) to {result.filepath} "
                              f"in {result.seconds:.1f} s")
        return {"FINISHED"}

    def _status(self, context, text=None):
        workspace = getattr(context, "workspace", None)
        if workspace is None:
            return
        if text is None and self._baker is not None:
            b = self._baker
            text = (f"VP-FFD: baking '{b.obj.name}' frame {b.current_frame} "
                    f"({b.done}/{b.total}); Esc to cancel")
        workspace.status_text_set(text)

    def _stop(self, context):
        wm = context.window_manager
        if getattr(self, "_timer", None) is not None:
            wm.event_timer_remove(self._timer)
            self._timer = None
        wm.progress_end()
        workspace = getattr(context, "workspace", None)
        if workspace is not None:
            workspace.status_text_set(None)

    def modal(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        try:
            return self._modal(context, event)
        except BaseException as exc:  # never leave a running bake (or its temporary file) behind
            self._stop(context)
            self._baker.abort()
            report(self, "ERROR", f"bake failed: {type(exc).__name__}: {exc}")
            return {"CANCELLED"}

    def _modal(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        baker = self._baker
        if event.type == "ESC" and event.value == "PRESS":
            self._stop(context)
            baker.abort()
            report(self, "WARNING", f"bake cancelled after {baker.done} of {baker.total} "
                                     f"frames; nothing was written to {baker.path}")
            return {"CANCELLED"}
        if event.type != "TIMER":
            return {"RUNNING_MODAL"}  # the scene changes frame under the user: keep input out
        deadline = time.perf_counter() + _MODAL_BUDGET_S
        try:
            finished = baker.step()
            while not finished and time.perf_counter() < deadline:
                finished = baker.step()
        except BakeError as exc:
            self._stop(context)
            baker.abort()
            report(self, "ERROR", str(exc))
            return {"CANCELLED"}
        context.window_manager.progress_update(baker.done)
        if not finished:
            self._status(context)
            return {"RUNNING_MODAL"}
        self._stop(context)
        status = self._finish()
        if status == {"FINISHED"} and self.use_switch:
            try:
                bpy.ops.ed.undo_push(message="VP-FFD: Switch to Cache")
            except RuntimeError:
                pass
        return status

    def cancel(self, context: bpy.types.Context) -> None:
        """Blender ended the modal operator (e.g. a file was loaded): discard the bake."""
        self._stop(context)
        if getattr(self, "_baker", None) is not None:
            self._baker.abort()


class OBJECT_OT_vpffd_use_cache(bpy.types.Operator):
    """Play the baked point cache through Blender's Mesh Cache modifier and disable the VP-FFD
    modifier (kept, to switch back): the file then needs no extension to render"""
    bl_idname = "object.vpffd_use_cache"
    bl_label = "Use Baked Cache"
    bl_options = {"REGISTER", "UNDO"}

    filepath: StringProperty(
        name="File", subtype="FILE_PATH", default="", options=_PATH_OPTIONS,
        description="Cache file; empty: the one the cache modifier already names")
    format: EnumProperty(name="Format", items=FORMAT_ITEMS, default="PC2", options={"SKIP_SAVE"})
    frame_start: IntProperty(
        name="Start", options={"SKIP_SAVE"},
        description="Scene frame of the cache's first frame (default: read from the file)")

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        ob = context.object
        return ob is not None and ob.type == "MESH" and modifier.find(ob) is not None

    def execute(self, context: bpy.types.Context) -> set[str]:
        ob = context.object
        try:
            if self.filepath:
                start = self.frame_start if self.properties.is_property_set("frame_start") else None
                switch_to_cache(ob, self.filepath, self.format, start, context.scene)
            else:
                cache = find_cache(ob)
                if cache is None or not cache.filepath:
                    raise BakeError("nothing baked yet: Bake first")
                switch_to_cache(ob, cache.filepath, cache.cache_format, cache.frame_start,
                                context.scene)
        except BakeError as exc:
            report(self, "ERROR", str(exc))
            return {"CANCELLED"}
        return {"FINISHED"}


class OBJECT_OT_vpffd_use_live(bpy.types.Operator):
    """Solve live again: enable the VP-FFD modifier and disable the cache modifier"""
    bl_idname = "object.vpffd_use_live"
    bl_label = "Use Live Solve"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        ob = context.object
        return ob is not None and ob.type == "MESH" and modifier.find(ob) is not None

    def execute(self, context: bpy.types.Context) -> set[str]:
        try:
            switch_to_live(context.object)
        except BakeError as exc:
            report(self, "ERROR", str(exc))
            return {"CANCELLED"}
        return {"FINISHED"}


classes = (OBJECT_OT_vpffd_bake, OBJECT_OT_vpffd_use_cache, OBJECT_OT_vpffd_use_live)


def draw_bake(layout, obj):
    """The Bake sub-panel of the VP-FFD panel for `obj`."""
    col = layout.column()
    cache = find_cache(obj)
    if cache is not None and using_cache(obj):
        col.label(text=f"Playing the {cache.cache_format} cache {cache.filepath}.", icon="FILE_CACHE")
        if any(m.show_viewport for m in modifier.find_all(obj)):
            col.label(text="A VP-FFD modifier is on too: its offsets add to the cache.",
                      icon="ERROR")
    row = col.row(align=True)
    row.operator("object.vpffd_bake", icon="EXPORT")
    if cache is not None:
        if using_cache(obj):
            row.operator("object.vpffd_use_live", icon="MOD_LATTICE")
        else:
            row.operator("object.vpffd_use_cache", icon="FILE_CACHE")
