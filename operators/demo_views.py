"""What the user sees once a demo is built: every 3D viewport of the window looking through the
demo's camera, and the views it had given back when the user's own scene is shown again."""
import bpy

#: The views the demos switched to their camera, to give back when the user's scene is shown
#: again: {area pointer: (name of the scene it showed, the view's settings)}. A 3D viewport's view
#: belongs to its area, not to the scene, so Blender alone would keep the camera view there.
_saved_views = {}
_VIEW_SETTINGS = ("view_perspective", "view_location", "view_rotation", "view_distance",
                  "view_camera_offset", "view_camera_zoom")


def _view_settings(rv3d):
    return {name: getattr(rv3d, name).copy() if hasattr(getattr(rv3d, name), "copy")
            else getattr(rv3d, name) for name in _VIEW_SETTINGS}


def restore_views():
    """Timer: give each saved view back once its area shows the scene it showed before the demo.
    Returns the seconds to the next look, or None when nothing is left to give back."""
    try:
        windows = bpy.context.window_manager.windows
    except AttributeError:
        _saved_views.clear()
        return None
    for window in windows:
        for area in window.screen.areas:
            saved = _saved_views.get(area.as_pointer())
            if saved is None or saved[0] != window.scene.name or area.type != "VIEW_3D":
                continue
            rv3d = area.spaces.active.region_3d
            for name, value in saved[1].items():
                setattr(rv3d, name, value)
            area.tag_redraw()
            del _saved_views[area.as_pointer()]
    scenes = set(bpy.data.scenes.keys())
    for key in [k for k, (scene, _) in _saved_views.items() if scene not in scenes]:
        del _saved_views[key]           # that scene is gone: nothing to give back to
    return 0.5 if _saved_views else None


def frame_views(context, user_scene=None):
    """Show the demo through its camera in every 3D viewport of the window, the camera's frame
    filling the view (as Numpad 0, then View > Cameras > Frame Camera Bounds). `user_scene`: the
    scene the window showed before the demo's own, whose views come back when it is shown again."""
    window, screen = context.window, getattr(context, "screen", None)
    if window is None or screen is None:
        return                          # no window (background, farm): nothing to frame
    for area in screen.areas:
        region = next((r for r in area.regions if r.type == "WINDOW"), None)
        if area.type != "VIEW_3D" or region is None or area.spaces.active.region_3d is None:
            continue
        rv3d = area.spaces.active.region_3d
        if user_scene is not None and area.as_pointer() not in _saved_views:
            _saved_views[area.as_pointer()] = (user_scene.name, _view_settings(rv3d))
        rv3d.view_perspective = "CAMERA"
        with context.temp_override(window=window, screen=screen, area=area, region=region):
            bpy.ops.view3d.view_center_camera()
    if _saved_views and not bpy.app.timers.is_registered(restore_views):
        bpy.app.timers.register(restore_views, first_interval=0.5)


def forget_views():
    """Stop giving views back and forget the saved ones (the extension is unregistered)."""
    if bpy.app.timers.is_registered(restore_views):
        bpy.app.timers.unregister(restore_views)
    _saved_views.clear()
