"""The VP-FFD modifiers in the stack: Geometry Nodes modifiers (their node group: node_group.py;
what they read: tap.py; where their offsets come from: solver_helper.py) that deform whatever
reaches their slot. Being real modifiers, they are toggled, reordered and removed like any other,
and a mesh may have any number (deformers.py pairs each with its settings). Here: finding them,
adding one, removing one, keeping its inputs in line with its settings."""
from .node_group import (GROUP_INPUT, GROUP_TAG, INVERT_INPUT, LATTICE_INPUT, SLOT_INPUT, SOLVER_INPUT,
                         get_input, hide_inputs, is_current, offset_node_group, set_input)
from .solver_helper import free_helper, helper


MODIFIER_NAME = "VP-FFD"


def set_lattice(mod, lattice):
    """Point VP-FFD modifier `mod`'s lattice input at `lattice` (an Object or None), when it differs."""
    if mod is not None:
        set_input(mod, LATTICE_INPUT, lattice)


def sync_inputs(mod, settings):
    """Bring modifier `mod`'s lattice, vertex-group, invert and slot inputs in line with its
    `settings`. Returns True when one changed (the object then waits for its next evaluation)."""
    if mod is None or settings is None:
        return False
    s = settings
    changed = [set_input(mod, LATTICE_INPUT, s.lattice),
               set_input(mod, GROUP_INPUT, s.vertex_group),
               set_input(mod, INVERT_INPUT, bool(s.invert_vertex_group and s.vertex_group)),
               set_input(mod, SLOT_INPUT, int(mod.persistent_uid))]
    return any(changed)


def find_all(obj):
    """Every VP-FFD modifier of the object, in stack order."""
    return [m for m in obj.modifiers
            if m.type == "NODES" and m.node_group is not None and m.node_group.get(GROUP_TAG)]


def find(obj):
    """The object's first VP-FFD modifier, or None."""
    found = find_all(obj)
    return found[0] if found else None


def add(obj):
    """A new VP-FFD modifier at the end of the stack, where Blender's Add Modifier puts one."""
    mod = obj.modifiers.new(MODIFIER_NAME, "NODES")
    prepare(obj, mod)
    return mod


def prepare(obj, mod, settings=None):
    """Give VP-FFD modifier `mod` the current node group, its solver helper and inputs that
    match `settings` (when given)."""
    if mod.node_group is None or not is_current(mod.node_group):
        mod.node_group = offset_node_group()
    hide_inputs(mod.node_group)
    if getattr(mod, "show_group_selector", False):
        mod.show_group_selector = False     # the node group is VP-FFD's own, not to be swapped
    helper(obj, mod)
    if settings is not None:
        sync_inputs(mod, settings)
    else:
        set_input(mod, SLOT_INPUT, int(mod.persistent_uid))
    return mod


def remove(obj, mod):
    """Remove VP-FFD modifier `mod` of `obj` and its solver helper."""
    if mod is not None:
        solver = get_input(mod, SOLVER_INPUT)
        obj.modifiers.remove(mod)
        free_helper(solver)
