"""Which objects an update must look at: the bound objects of the scene, and the bound objects
linked from a library that the depsgraph evaluates only through a collection instance (they are
not in `scene.objects`).

Every VP-FFD modifier uses a VP-FFD node group (node_group.py; a rig linked from a library brings
its library's group), so the objects that may be bound are the users of those groups: Blender's
own `user_map` finds them in C, and it runs again only when a group's user count changes (a
modifier added, copied or removed, an object deleted) or a file, an undo step or a library brings
new data (`forget`). docs/stack.md says why the scene's own objects are still found by walking
`scene.objects`."""
import bpy

from . import deformers
from .node_group import GROUP_TAG

_groups = {"count": -1, "groups": ()}       # the VP-FFD node groups, while bpy.data's count holds
_candidates = {"key": None, "objects": ()}  # users of those groups, while their user counts hold


def forget():
    """Look again on the next call (a file was loaded, undo ran: the data are new)."""
    _groups["count"] = -1
    _candidates["key"] = None


def _vpffd_groups():
    node_groups = bpy.data.node_groups
    if len(node_groups) != _groups["count"]:
        _groups["groups"] = tuple(ng for ng in node_groups if ng.get(GROUP_TAG))
        _groups["count"] = len(node_groups)
    return _groups["groups"]


def candidates():
    """Every object with a VP-FFD modifier, in every scene and library, in a fixed order
    (library, then name: the first of duplicates that share a solver helper keeps it)."""
    try:
        groups = _vpffd_groups()
        key = tuple((ng.session_uid, ng.users) for ng in groups)
    except ReferenceError:                   # a group was removed
        forget()
        groups = _vpffd_groups()
        key = tuple((ng.session_uid, ng.users) for ng in groups)
    if key != _candidates["key"]:
        found = set()
        if groups:
            for users in bpy.data.user_map(subset=groups, value_types={"OBJECT"}).values():
                found |= users
        _candidates["objects"] = tuple(sorted(
            found, key=lambda ob: (ob.library.filepath if ob.library else "", ob.name)))
        for ob in _candidates["objects"]:
            deformers.reference_settings(ob)     # a file opened, a modifier added: before any save
        _candidates["key"] = key
    return _candidates["objects"]


def _bound(ob):
    try:
        return ob.type == "MESH" and deformers.is_bound(ob)
    except ReferenceError:                   # removed since the candidates were found
        forget()
        return False


def in_scene(scene):
    """The bound mesh objects of `scene` (what load and undo prepare)."""
    return [ob for ob in scene.objects if _bound(ob)]


def bound_objects(scene, depsgraph):
    """The bound mesh objects of `scene`, then those linked from a library (no override) that
    `depsgraph` evaluates through a collection instance."""
    found = in_scene(scene)
    for ob in candidates():
        if ob.library is not None and _bound(ob) and ob.evaluated_get(depsgraph).is_evaluated \
                and ob not in found:
            found.append(ob)
    return found
