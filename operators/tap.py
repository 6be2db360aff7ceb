"""Reading the tap: what reached the VP-FFD slot (positions, weights and, when asked, the
triangles), from the end of the evaluated object's stack (node_group.py makes it)."""
import numpy as np

from .node_group import (CORNER_ATTRIBUTES, COUNT_ATTRIBUTE, FACE_ATTRIBUTE, PACK, PACKED_POSITIONS,
                         PACKED_WEIGHTS, POINT_POSITION, SLOT_ATTRIBUTE, TAP_ATTRIBUTE, WEIGHT_ATTRIBUTE)


def _tap_cloud(ob_eval, depsgraph):
    """(a point cloud that carries the tap or None, an object to keep alive while it is read,
    whether it is the instances' point cloud, i.e. the packed tap of Blender 4.4+)."""
    get = getattr(ob_eval, "evaluated_geometry", None)
    if get is not None:        # newer Blender: the object's own geometry set
        try:
            geometry = get()
        except TypeError:      # tagged for an evaluation that has not run yet
            return None, None, False
        instances = geometry.instances_pointcloud()
        if instances is not None and instances.attributes.get(TAP_ATTRIBUTE) is not None:
            return instances, (geometry, instances), True
        return geometry.pointcloud, geometry, False
    original = ob_eval.original
    for inst in depsgraph.object_instances:
        # Before that, the non-mesh components of a mesh object appear as instances of it.
        if inst.is_instance and inst.object.type == "POINTCLOUD" and inst.parent is not None \
                and inst.parent.original == original:
            return inst.object.data, None, False
    return None, None, False


def _marked(attrs, name, n, slot):
    """(n,) bool: the elements marked with boolean attribute `name` that VP-FFD modifier `slot`
    made (every marked one for slot None), or None when the mark is missing."""
    mark = attrs.get(name)
    if mark is None:
        return None
    marked = np.empty(n, bool)
    mark.data.foreach_get("value", marked)
    if slot is not None:
        made_by = attrs.get(SLOT_ATTRIBUTE)
        if made_by is None:
            return None
        slots = np.empty(n, np.int32)
        made_by.data.foreach_get("value", slots)
        marked &= slots == np.int32(slot)
    return marked


def _packed_tap(attrs, n, slot, strided=True):
    """(is_tap (n,) bool, positions (V, 3) float32, weights (V,) float32) of a packed instance
    tap (see PACK) of VP-FFD modifier `slot`, or None when its attributes are missing. It is read
    from the first ceil(V / PACK) instances the slot marked: a later modifier may join copies of
    them, which carry the same values. `strided`: the layout of node group version 8 and newer (vertex k * m + i is
    instance i's k-th packed value, m instances), else the older one (vertex PACK * i + k): a
    linked group is not rebuilt and keeps writing the older layout."""
    is_tap, count = _marked(attrs, TAP_ATTRIBUTE, n, slot), attrs.get(COUNT_ATTRIBUTE)
    if is_tap is None or count is None:
        return None
    marked = np.flatnonzero(is_tap)
    if len(marked) == 0:
        return None
    counts = np.empty(n, np.int32)
    count.data.foreach_get("value", counts)
    V = int(counts[marked[0]])
    m = -(-V // PACK)
    if V < 0 or m > len(marked):
        return None
    # Straight into (PACK, n, ...) buffers; with every element the slot's own (the usual case)
    # they are, layer after layer, the vertices in order, with no copy.
    vec, val = np.empty((PACK, n, 3), np.float32), np.empty((PACK, n), np.float32)
    for k in range(PACK):
        p, q = attrs.get(PACKED_POSITIONS[k]), attrs.get(PACKED_WEIGHTS[k])
        if p is None or q is None:
            return None
        p.data.foreach_get("vector", vec[k].reshape(-1))
        q.data.foreach_get("value", val[k])
    if m < n:           # the face tap, other slots' taps, or copies that a later modifier joined
        own = marked[:m]
        vec, val = vec[:, own], val[:, own]
    if not strided:
        vec, val = vec.transpose(1, 0, 2), val.T
    return is_tap, vec.reshape(-1, 3)[:V], val.reshape(-1)[:V]


def read_tap(ob_eval, depsgraph, slot=None, strided=True):
    """(positions (V, 3) float32, weights (V,) float32, triangles (F, 3) int64 or None) of the
    geometry that reached the slot of VP-FFD modifier `slot` (its persistent_uid; None: the only
    one) in this evaluation, in the object's space (`strided`: how its node group packs the tap of
    Blender 4.4+, `node_group.packs_by_stride`); the
    triangles only while the modifier's Tap Faces input is on. None when no tap reached the end of
    the stack (the modifier is off, or a later Geometry Nodes modifier dropped point clouds)."""
    cloud, _alive, from_instances = _tap_cloud(ob_eval, depsgraph)
    if cloud is None:
        return None
    attrs = cloud.attributes
    if from_instances:
        n = len(attrs.get(TAP_ATTRIBUTE).data)
        packed = _packed_tap(attrs, n, slot, strided)
        if packed is None:
            return None
        is_tap, co, w = packed
    else:
        # (groups older than version 8 have no POINT_POSITION)
        position, weight = attrs.get(POINT_POSITION) or attrs.get("position"), attrs.get(WEIGHT_ATTRIBUTE)
        if position is None:
            return None
        n = len(position.data)
        is_tap = _marked(attrs, TAP_ATTRIBUTE, n, slot)
        if is_tap is None:
            return None
        co = np.empty(n * 3, np.float32)
        position.data.foreach_get("vector", co)
        w = np.ones(n, np.float32)
        if weight is not None and weight.data_type == "FLOAT":
            weight.data.foreach_get("value", w)
    co = co.reshape(-1, 3)
    tris = None
    is_face = _marked(attrs, FACE_ATTRIBUTE, n, slot)
    if is_face is not None:
        corners = []
        for name in CORNER_ATTRIBUTES:
            attr = attrs.get(name)
            if attr is None:
                break
            c = np.empty(n, np.int32)
            attr.data.foreach_get("value", c)
            corners.append(c[is_face])
        if len(corners) == 3:
            tris = np.stack(corners, 1).astype(np.int64)
    if not from_instances and not is_tap.all():  # the face tap, or points a later modifier joined
        co, w = co[is_tap], w[is_tap]
    if not from_instances:
        count = attrs.get(COUNT_ATTRIBUTE)     # (a group older than version 8 has none)
        if count is not None and len(co):
            first = np.empty(n, np.int32)
            count.data.foreach_get("value", first)
            V = int(first[np.flatnonzero(is_tap)[0]])
            if 0 <= V <= len(co):               # the first of copies that a later modifier joined
                co, w = co[:V], w[:V]
    return co, w, tris
