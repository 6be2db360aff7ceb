"""The Mesh Cache modifier that plays a baked VP-FFD cache: finding it, and whether it plays."""

CACHE_MODIFIER_NAME = "VP-FFD Cache"


def find_cache(obj):
    """The object's VP-FFD cache modifier (a Mesh Cache modifier named "VP-FFD Cache"), or None."""
    mod = obj.modifiers.get(CACHE_MODIFIER_NAME)
    return mod if mod is not None and mod.type == "MESH_CACHE" else None


def using_cache(obj):
    """True when the object plays its baked cache (the cache modifier is on)."""
    mod = find_cache(obj)
    return mod is not None and (mod.show_viewport or mod.show_render)
