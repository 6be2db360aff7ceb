"""The Outside modes: what a lattice (or a cage) does to the vertices outside it, as one table
(docs/design.md, "Outside the lattice"; docs/architecture.md, "A new Outside mode").

Each `OutsideMode` names the mode once and carries everything the rest of the extension asks of
it: the label and description the settings show, whether it has a distance (Falloff Distance),
which controls it applies to, and its factor on a vertex's influence. The extension's settings
(`obj.vpffd.outside`, `obj.vpffd.cage_outside`) are built from `enum_items`, the panel draws
`modes(kind)`, the frame and the bind look modes up with `mode(name)`.

"Outside vertices stay where they are" is STAY for lattices and cages alike; INSIDE, its name for
lattices in earlier versions, is an alias: scripts that set it and files that stored it read STAY.
"""
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from .falloff import INSIDE_SLACK, box_distance, profile


def _falloff_factor(d, distance):
    distance = float(distance)
    if not (np.isfinite(distance) and distance > 0):
        raise ValueError(f"the falloff distance must be a positive number, got {distance!r}")
    return profile(d / distance)


def _stay_factor(d, distance):
    return (d <= INSIDE_SLACK).astype(np.float64)


@dataclass(frozen=True)
class OutsideMode:
    """One Outside mode. `factor(d, distance)`: (V,) factor on the influence of vertices at
    distance d (V,) from the lattice's rest box (lattice-size units per side), or None for 1
    everywhere (nothing to compute). `kinds`: the controls it applies to ("lattice", "cage")."""
    name: str
    label: str
    description: str
    has_distance: bool = False
    kinds: tuple = ("lattice", "cage")
    factor: Optional[Callable] = None
    follows: bool = False            #: outside vertices follow the boundary
    aliases: tuple = ()              #: earlier names, still accepted


#: The modes, in the order the settings list them (their stored numbers follow this order per kind).
MODES = (
    OutsideMode("FOLLOW", "Follow", "Vertices outside follow the boundary (a lattice: as with "
                "Blender's Lattice modifier; a cage: the closest point of its region's boundary)",
                follows=True),
    OutsideMode("FALLOFF", "Falloff", "The deformation fades out smoothly outside the lattice, over "
                "Falloff Distance, with no seam at the lattice's faces; the volume is still kept",
                has_distance=True, kinds=("lattice",), factor=_falloff_factor),
    OutsideMode("STAY", "Stay", "Vertices outside the lattice (or the cage's region) do not move",
                factor=_stay_factor, aliases=("INSIDE",)),
)

_BY_NAME = {name: m for m in MODES for name in (m.name,) + m.aliases}


def modes(kind="lattice"):
    """The modes that apply to `kind` ("lattice" or "cage"), in the settings' order."""
    return tuple(m for m in MODES if kind in m.kinds)


def names(kind="lattice"):
    """The names of `modes(kind)` (aliases left out)."""
    return tuple(m.name for m in modes(kind))


def mode(name, kind="lattice"):
    """The `OutsideMode` called `name` (or one of its aliases; any case) for `kind`; ValueError
    naming the choices for another name."""
    m = _BY_NAME.get(str(name).upper())
    if m is None or kind not in m.kinds:
        raise ValueError(f"outside must be one of {', '.join(names(kind))}, got {name!r}")
    return m


def enum_items(kind="lattice"):
    """[(identifier, label, description, number)] for a Blender EnumProperty of `kind`: the modes
    numbered in order (the numbers a .blend stores), then each alias with its mode's number, so
    that files and scripts using an earlier name read the mode under its name now."""
    items = [(m.name, m.label, m.description, i) for i, m in enumerate(modes(kind))]
    items += [(alias, m.label, f"{m.description} (earlier name of {m.label})", i)
              for i, m in enumerate(modes(kind)) for alias in m.aliases]
    return items


def outside_factor(lattice, verts, name="FOLLOW", distance=0.5):
    """(V,) factor on the influence of `verts` (V, 3) (lattice space) for the Outside mode `name`
    of a `Lattice`; `distance`: the falloff distance in lattice-size units (Falloff only, > 0)."""
    m = mode(name)
    if m.factor is None:
        return np.ones(len(verts))
    return m.factor(box_distance(lattice, verts), distance)
