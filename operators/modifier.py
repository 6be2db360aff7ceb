"""The VP-FFD entry in the modifier stack: a Geometry Nodes modifier (its node group:
node_group.py; what it reads: tap.py; where its offsets come from: solver_helper.py) that deforms
whatever reaches its slot. Being a real modifier, it is toggled, reordered and removed like any
other. Here: finding it, adding it, removing it, keeping its inputs in line with the settings."""
from .node_group import (GROUP_INPUT, GROUP_TAG, INVERT_INPUT, LATTICE_INPUT, SOLVER_INPUT, get_input,
                         hide_inputs, is_current, offset_node_group, set_input)
from .solver_helper import free_helper, helper


MODIFIER_NAME = "VP-FFD"


def set_lattice(obj, lattice):
    """Point the VP-FFD modifier's lattice input at `lattice` (an Object or None), when it differs."""
    mod = find(obj)
    if mod is not None:
        set_input(mod, LATTICE_INPUT, lattice)


def sync_inputs(obj, mod=None):
    """Bring the modifier's lattice, vertex-group and invert inputs in line with obj.vpffd.
    Returns True when one changed (the object then waits for its next evaluation)."""
    mod = mod or find(obj)
    if mod is None:
        return False
    s = obj.vpffd
    changed = [set_input(mod, LATTICE_INPUT, s.lattice),
               set_input(mod, GROUP_INPUT, s.vertex_group),
               set_input(mod, INVERT_INPUT, bool(s.invert_vertex_group and s.vertex_group))]
    return any(changed)


def find_all(obj):
    """Every VP-FFD modifier of the object (one is supported; a duplicated one is reported)."""
    return [m for m in obj.modifiers
            if m.type == "NODES" and m.node_group is not None and m.node_group.get(GROUP_TAG)]


def find(obj):
    """The object's VP-FFD modifier (the first, if there are several), or None."""
    found = find_all(obj)
    return found[0] if found else None


def ensure(obj):
    """Find or add the VP-FFD modifier. A new one goes where Blender's Add Modifier puts a
    modifier, the end of the stack; an existing one stays where the user put it."""
    mod = find(obj)
    if mod is None:
        mod = obj.modifiers.new(MODIFIER_NAME, "NODES")
    if mod.node_group is None or not is_current(mod.node_group):
        mod.node_group = offset_node_group()
    hide_inputs(mod.node_group)
    if getattr(mod, "show_group_selector", False):
        mod.show_group_selector = False     # the node group is VP-FFD's own, not to be swapped
    helper(obj, mod)
    sync_inputs(obj, mod)
    return mod


def remove(obj):
    mod = find(obj)
    if mod is not None:
        solver = get_input(mod, SOLVER_INPUT)
        obj.modifiers.remove(mod)
        free_helper(solver)


# ------------------------------------------------------------------------------ solver helper
