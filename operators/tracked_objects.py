"""Which objects an update must look at, found without going through the objects of the scene
(a shot holds thousands; docs/stack.md, "A shot's size"): the users of VP-FFD's node groups.

Every VP-FFD modifier uses a VP-FFD node group (node_group.py; a rig linked from a library brings
its library's group), so the objects that may be bound are the users of those groups. Blender's
own `user_map` finds them in C, and it runs again only when a group's user count changes (a
modifier added, copied or removed, an object deleted) or a file, an undo step or a library brings
new data (`forget`). Of those, an update takes the ones its depsgraph evaluates (the scene's
shown objects, and objects a collection instance shows) and the scene's hidden ones (their panel
says so); which scenes hold a hidden one is asked once, again after collections change."""
import bpy

from . import deformers, node_group

_groups = {"key": None, "groups": ()}       # the VP-FFD node groups, while their count and tags hold
_candidates = {"key": None, "objects": ()}  # users of those groups, while their user counts hold
_scenes = {"key": None, "of": {}}           # object session_uid -> the scenes holding it


def forget():
    """Look again on the next call (a file was loaded, undo ran: the data are new)."""
    _groups["key"] = None
    _candidates["key"] = None
    _scenes["key"] = None


def _vpffd_groups():
    node_groups = bpy.data.node_groups
    key = (len(node_groups), node_group.builds[0])     # a group added, removed or tagged
    if key != _groups["key"]:
        _groups["groups"] = tuple(ng for ng in node_groups if ng.get(node_group.GROUP_TAG))
        _groups["key"] = key
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
        # An object whose VP-FFD modifier was just removed (X, Ctrl+A) uses no group any more,
        # but is still bound until an update lets go of it (update.release): keep it until then.
        for ob in _candidates["objects"] if _candidates["key"] is not None else ():
            try:
                if ob not in found and ob.type == "MESH" and deformers.is_bound(ob):
                    found.add(ob)
            except ReferenceError:           # removed
                pass
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


def local_bound():
    """The bound mesh objects of this file (not linked from a library), in every scene or none:
    what loading a file and undo prepare."""
    return [ob for ob in candidates() if ob.library is None and _bound(ob)]


def scenes_of(ob):
    """The scenes that hold object `ob` (in a collection of theirs, however deep, hidden or
    excluded or not). Asked of Blender once per object, then again after any collection or scene
    changed (`collections_changed`, `forget`)."""
    key = (_candidates["key"], len(bpy.data.collections), len(bpy.data.scenes))
    if key != _scenes["key"]:
        _scenes["of"] = {}
        _scenes["key"] = key
    uid = ob.session_uid
    if uid not in _scenes["of"]:
        _scenes["of"][uid] = frozenset(s.session_uid for s in ob.users_scene)
    return _scenes["of"][uid]


def collections_changed():
    """An object was linked into or out of a collection, or a collection into or out of another
    (the depsgraph says so: `Depsgraph.id_type_updated('COLLECTION')`): ask the scenes again."""
    _scenes["key"] = None


def bound_objects(scene, depsgraph):
    """The bound mesh objects that an update of `scene` by `depsgraph` must look at, in the order
    of `candidates`: those `depsgraph` evaluates (shown in the scene, or linked from a library and
    shown by a collection instance), and the scene's own that it does not evaluate (hidden: the
    panel says so). An override's linked reference is neither."""
    if depsgraph.id_type_updated("COLLECTION"):
        collections_changed()
    found = []
    for ob in candidates():
        try:
            if ob.type != "MESH":
                continue
            evaluated = ob.evaluated_get(depsgraph).is_evaluated
            if not evaluated and (ob.library is not None or scene.session_uid not in scenes_of(ob)):
                continue
        except ReferenceError:               # removed since the candidates were found
            forget()
            continue
        if _bound(ob):
            found.append(ob)
    return found


def shown(view_layer):
    """The bound mesh objects of this file visible in `view_layer` (what the overlay draws)."""
    return [ob for ob in candidates()
            if ob.library is None and ob.visible_get(view_layer=view_layer) and _bound(ob)]
