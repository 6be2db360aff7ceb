"""What Bind saves with a bound object, and where: the names of the attributes and custom
properties (on the solver helper; on the mesh in files of earlier versions), their reads and writes."""
import numpy as np

from . import meshio


LEGACY_ATTRIBUTES = ("vpffd_offset", "vpffd_weight")  # written by earlier versions


PIN_ATTRIBUTE = "vpffd_pin"         # pinned vertices, in files of earlier versions


PIN_PROPERTY = "vpffd_pins"         # on the solver helper: the pinned vertices' indices


JACOBIAN_ATTRIBUTE = "vpffd_jacobian"  # det of the deformation's Jacobian (on request)


CAGE_REST_PROPERTY = "vpffd_cage_rest"  # on the helper: the cage's points at Bind, flat, cage space


BIND_VOLUME_PROPERTY = "vpffd_bind_volumes"  # on the helper: each island's volume at Bind (object space)


def float_attribute(mesh, name, values=None):
    """Write (V,) float point attribute `name`, or read it (None when missing)."""
    attr = mesh.attributes.get(name)
    if values is None:
        if attr is None or attr.data_type != "FLOAT" or len(attr.data) != len(mesh.vertices):
            return None
        out = np.empty(len(mesh.vertices), np.float32)
        attr.data.foreach_get("value", out)
        return out.astype(np.float64)
    data = meshio.float32_or_raise(values, f"the values of '{name}'")
    if attr is not None:
        mesh.attributes.remove(attr)
    attr = mesh.attributes.new(name, "FLOAT", "POINT")
    attr.data.foreach_set("value", data)
    return attr


def saved(helper, obj, name):
    """What Bind saved under `name`: on the solver helper (or on the mesh, in earlier versions)."""
    value = helper.get(name) if helper is not None else None
    return obj.data.get(name) if value is None else value


def remove_attribute(mesh, name):
    """Remove attribute (or custom property) `name` of the mesh, when it has one."""
    attr = mesh.attributes.get(name)
    if attr is not None:
        mesh.attributes.remove(attr)
    if name in mesh:
        del mesh[name]
