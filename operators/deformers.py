"""Which VP-FFD settings belong to which VP-FFD modifier: a mesh may have any number of VP-FFD
modifiers anywhere in its stack, each with its own lattice, settings, bind and status.

The settings of the first deformer are `Object.vpffd` (what scripts and files of earlier versions
use); every further one has an entry in `Object.vpffd_extra`. Each names its modifier by the
modifier's `persistent_uid` (Blender keeps it when the stack is reordered, the modifier renamed
or the object duplicated). Settings whose `modifier_uid` is still 0 (files of earlier versions,
which allowed one VP-FFD modifier) belong to the first VP-FFD modifier that no other settings
name. Nothing here writes, except `claim`, `drop` and `reference_settings`."""
import dataclasses

from . import modifier, node_group


@dataclasses.dataclass(frozen=True, eq=False)
class Deformer:
    """One VP-FFD deformer of a mesh: its modifier (None when it is gone or not added yet) and
    its settings (`obj.vpffd` or an entry of `obj.vpffd_extra`)."""
    obj: object
    mod: object
    settings: object
    #: the modifier's persistent_uid (the settings' record of it when the modifier is gone), read
    #: at once: it stays the deformer's key after its modifier is removed
    uid: int = dataclasses.field(init=False)
    key: tuple = dataclasses.field(init=False)   #: of its cached state and status

    def __post_init__(self):
        uid = self.mod.persistent_uid if self.mod is not None else self.settings.modifier_uid
        object.__setattr__(self, "uid", uid)
        object.__setattr__(self, "key", (self.obj.session_uid, uid))

    @property
    def is_first(self):
        """Whether its settings are `obj.vpffd` (the deformer scripts of earlier versions meant)."""
        return self.settings == self.obj.vpffd


def extras(obj):
    return getattr(obj, "vpffd_extra", ())


def _first_is_free(obj, mods):
    """Whether `obj.vpffd` names no existing VP-FFD modifier (0, or its modifier is gone)."""
    uid = obj.vpffd.modifier_uid
    return uid == 0 or not any(m.persistent_uid == uid for m in mods)


def settings_of(obj, mod, mods=None):
    """The settings of VP-FFD modifier `mod` of `obj`, or None (a modifier no settings name:
    added by copying another one in the stack)."""
    uid = mod.persistent_uid
    if obj.vpffd.modifier_uid == uid:
        return obj.vpffd
    for entry in extras(obj):
        if entry.modifier_uid == uid:
            return entry
    mods = modifier.find_all(obj) if mods is None else mods
    # Blender gives a modifier a new uid in some cases (those a library override inserted, on
    # load): its Slot input still holds the uid its settings were synced with.
    slot = node_group.get_input(mod, node_group.SLOT_INPUT)
    if slot and slot != uid and not any(m.persistent_uid == slot for m in mods):
        for s in (obj.vpffd, *extras(obj)):
            if s.modifier_uid == slot:
                return s
    if _first_is_free(obj, mods):
        named = {e.modifier_uid for e in extras(obj)}
        unnamed = [m for m in mods if m.persistent_uid not in named]
        if unnamed and unnamed[0] == mod:
            return obj.vpffd
    return None


def modifier_of(obj, settings):
    """The VP-FFD modifier that `settings` belong to, or None."""
    mods = modifier.find_all(obj)
    for m in mods:
        if settings_of(obj, m, mods) == settings:
            return m
    return None


def all_of(obj):
    """Every deformer of `obj` in stack order, then bound settings whose modifier is gone (the
    update lets go of those)."""
    mods = modifier.find_all(obj)
    found = []
    for m in mods:
        s = settings_of(obj, m, mods)
        if s is not None:
            found.append(Deformer(obj, m, s))
    for s in (obj.vpffd, *extras(obj)):
        if s.is_bound and not any(d.settings == s for d in found):
            found.append(Deformer(obj, None, s))
    return found


def bound(obj):
    """The bound deformers of `obj` (stack order; those whose modifier is gone last)."""
    if not is_bound(obj):
        return []
    return [d for d in all_of(obj) if d.settings.is_bound]


def is_bound(obj):
    """Whether any VP-FFD deformer of `obj` is bound."""
    return obj.vpffd.is_bound or any(e.is_bound for e in extras(obj))


def first(obj):
    """The deformer of `obj.vpffd` (its modifier may be None)."""
    return Deformer(obj, modifier_of(obj, obj.vpffd), obj.vpffd)


def shown(obj):
    """The deformer the panel shows: the active modifier when it is a VP-FFD one, as the Geometry
    Nodes editor follows the active modifier; else the first VP-FFD modifier; else `first`."""
    mods = modifier.find_all(obj)
    active = getattr(obj.modifiers, "active", None)
    for m in ([active] if active in mods else []) + mods:
        s = settings_of(obj, m, mods)
        if s is not None:
            return Deformer(obj, m, s)
    return first(obj)


def named(obj, name=""):
    """The deformer of the VP-FFD modifier called `name`; "" gives `first` (what an operator
    called from a script without naming a modifier acts on). KeyError when there is none."""
    if not name:
        return first(obj)
    mod = obj.modifiers.get(name)
    if mod is None or mod not in modifier.find_all(obj):
        raise KeyError(f"'{obj.name}' has no VP-FFD modifier called '{name}'")
    s = settings_of(obj, mod)
    if s is None:
        s = claim(obj, mod)
    return Deformer(obj, mod, s)


def reference_settings(obj):
    """Give the linked object that library override `obj` overrides its VP-FFD settings, in memory
    (reading `Object.vpffd` makes them; nothing is written to the library). Blender keeps an
    override's changes as the differences from its reference, found property by property where
    the reference has the settings too; where it has none (a rig saved without VP-FFD's settings
    on that object), the whole of `vpffd` is recorded as one pointer to replace, which Blender
    cannot apply when the file is opened again, and every VP-FFD setting of the override is lost
    (docs/stack.md, "Library overrides"). Called for every override VP-FFD binds and looks at, so
    the reference has them whenever Blender compares (on save, and on every undo step)."""
    override = getattr(obj, "override_library", None)
    reference = override.reference if override is not None else None
    if reference is not None and obj.library is None:
        reference.vpffd


def claim(obj, mod):
    """The settings of `mod`, made when none name it: `obj.vpffd` when it names no bound
    deformer, else a new entry of `obj.vpffd_extra`. Writes the modifier's uid into them."""
    reference_settings(obj)
    mods = modifier.find_all(obj)
    s = settings_of(obj, mod, mods)
    if s is None:
        if _first_is_free(obj, mods) and not obj.vpffd.is_bound:
            s = obj.vpffd
        else:
            s = obj.vpffd_extra.add()
    if s.modifier_uid != mod.persistent_uid:
        s.modifier_uid = mod.persistent_uid
    return s


_NOT_COPIED = {"rna_type", "name", "is_bound", "modifier_uid", "applied_lattice", "enabled"}


def copy_settings(source, target):
    """Copy every setting of `source` to `target` except what belongs to one binding."""
    for name, prop in source.bl_rna.properties.items():
        if name not in _NOT_COPIED and not prop.is_readonly:
            setattr(target, name, getattr(source, name))


def drop(d):
    """Let go of the settings of a deformer whose modifier is gone: `obj.vpffd` stays as it is
    (its settings wait for a later Bind); an entry of `obj.vpffd_extra` names no modifier any
    more but stays in place: keyframes and drivers address the entries by their index
    (`vpffd_extra[2].volume_scale`), so removing one would hand the next one's animation on."""
    if not d.is_first and d.settings.modifier_uid:
        d.settings.modifier_uid = 0


def evaluated_settings(d, ob_eval):
    """The settings of deformer `d` on the evaluated object `ob_eval` (animated settings have the
    evaluated frame's values there: a render's depsgraph does not write them back)."""
    if d.is_first:
        return ob_eval.vpffd
    uid = d.settings.modifier_uid
    for entry in extras(ob_eval):
        if entry.modifier_uid == uid:
            return entry
    return d.settings


def label(d):
    """Words naming the deformer among the object's VP-FFD modifiers, e.g. "'Head' (1 of 2)";
    "" when it is the only one."""
    mods = modifier.find_all(d.obj)
    if len(mods) < 2 or d.mod is None:
        return ""
    return f"'{d.mod.name}' ({mods.index(d.mod) + 1} of {len(mods)})"
