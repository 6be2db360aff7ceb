"""A Geometry Nodes modifier's input values, read and written the same way on every Blender.

Up to Blender 5.1 the values of a Geometry Nodes modifier's inputs are ID properties of the
modifier, keyed by the socket identifier (`mod["Socket_2"]`). From 5.2 on the modifier takes no ID
properties at all (`mod.get` raises "this type doesn't support IDProperties"); each input is an RNA
struct `mod.properties.inputs.<identifier>` whose `value` is writable (the attribute holding the
struct is not). This module is the only place that knows both: everything else passes socket
identifiers and values.
"""


def _slot(mod, identifier):
    """The RNA struct of input `identifier` (Blender 5.2+), or None on the ID-property API."""
    inputs = getattr(getattr(mod, "properties", None), "inputs", None)
    if inputs is None:
        return None
    slot = getattr(inputs, identifier, None)
    if slot is None:
        raise KeyError(f"the modifier {mod.name!r} has no input {identifier!r}")
    return slot


def get(mod, identifier):
    """The value of input `identifier` (an ID, a number, a string, ...; None for an empty
    object field or an input never set)."""
    slot = _slot(mod, identifier)
    if slot is not None:
        return slot.value
    return mod.get(identifier)


def put(mod, identifier, value):
    """Write input `identifier`. Writing an input tags nothing for evaluation by itself."""
    slot = _slot(mod, identifier)
    if slot is not None:
        slot.value = value
    else:
        mod[identifier] = value


def value_sockets(group):
    """The node group's interface input sockets that hold a value (not the geometry)."""
    return [item for item in group.interface.items_tree
            if getattr(item, "in_out", None) == "INPUT" and item.socket_type != "NodeSocketGeometry"]


def identifiers(mod):
    """The identifiers of the modifier's input sockets that hold a value (not the geometry)."""
    return [] if mod.node_group is None else [item.identifier for item in value_sockets(mod.node_group)]


def values(mod):
    """{identifier: value} of every input that holds a value."""
    return {key: get(mod, key) for key in identifiers(mod)}
