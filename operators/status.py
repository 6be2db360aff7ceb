"""What the last update of each bound deformer found, for the panel, the status line and scripts:
the typed `Status`, kept per deformer (deformers.py), and the words for vertices outside the
lattice."""
import dataclasses
import logging
from typing import Optional

from ..vpffd_addon import outside as outside_modes
from . import deformers

log = logging.getLogger(__name__)

_stats = {}   # deformer key (object session_uid, modifier uid) -> Status shown by the panel


@dataclasses.dataclass
class Status:
    """What the last update of an object found: the panel shows these fields. Volumes are
    percentages of the reference volume: the volume that reached the VP-FFD slot, or with
    Target: Bind the volume at Bind; None where not known."""
    error: Optional[str] = None            #: why nothing (or only the input) is shown, in words
    switched_off: bool = False             #: the modifier is off in the viewport
    paused: Optional[str] = None           #: why VP-FFD is not solving now (no figures then)
    warnings: tuple = ()                   #: what the solve could not do, in words
    volume_percent: Optional[float] = None
    plain_percent: Optional[float] = None  #: what the plain Lattice modifier would give
    input_volume: Optional[float] = None   #: in lattice space
    seconds: Optional[float] = None        #: the whole update
    core_seconds: Optional[float] = None   #: the frame pipeline alone
    backend: str = "CPU"
    backend_reason: str = ""
    n_verts: Optional[int] = None          #: points that reached the slot
    closed: Optional[bool] = None          #: whether their faces close a volume
    encloses_nothing: bool = False         #: open, with no volume about the lattice's centre
    mirrored: bool = False                 #: the lattice turns the volume's sign (a mirror)
    folds: Optional[int] = None            #: vertices where the lattice folds space
    rebound: bool = False                  #: whether this update embedded the input anew
    outside: Optional[int] = None          #: points outside the lattice's box or cage's region
    outside_follow: bool = True            #: whether those follow the boundary (else they stay)
    outside_mode: str = "FOLLOW"           #: the lattice's Outside setting as solved
    falloff: Optional[int] = None          #: points outside that the falloff moves partly
    still: Optional[int] = None            #: points with no influence (left exactly in place)
    beyond: Optional[int] = None           #: points the Outside setting keeps still
    target_from: Optional[str] = None      #: "bind" when the volume at Bind is the reference
    input_percent: Optional[float] = None  #: the input's volume, with Target: Bind
    editing: bool = False                  #: solved from the mesh as edited (its Edit Mode)
    kernels: Optional[str] = None          #: on the CPU: "compiled" or "NumPy"
    kernels_why: Optional[str] = None      #: why NumPy's kernels ran, in words
    awaits_kernels: bool = False           #: NumPy solved while the compiled kernels compiled


def deformer_of(target):
    """`target` itself when it is a `deformers.Deformer`; for a mesh object, its first deformer
    (what scripts written for one VP-FFD modifier per mesh mean)."""
    return target if isinstance(target, deformers.Deformer) else deformers.first(target)


def status(target):
    """The typed `Status` of the last update of deformer `target` (a `deformers.Deformer`, or a
    mesh object for its first deformer); an empty one before any."""
    return _stats.get(deformer_of(target).key) or Status()


def stats(target):
    """`status(target)` as a dict of the fields that are set (for scripts)."""
    return {k: v for k, v in dataclasses.asdict(status(target)).items() if v is not None}


_reported = {}  # deformer key -> last error printed, so a failing frame range logs once


def set_status(d, **values):
    """Record the `Status` of deformer `d`'s update (and log a new error once)."""
    d = deformer_of(d)
    st = _stats[d.key] = Status(**values)
    if st.error and _reported.get(d.key) != st.error:
        where = d.obj.name + (f" ({d.mod.name})" if d.mod is not None and deformers.label(d) else "")
        log.warning("%s: %s", where, st.error)  # the console and farm logs, once per new problem
    _reported[d.key] = st.error
    return st


def outside_message(info, is_cage):
    """Words for `info.outside` points of `info.n_verts` outside the lattice or cage."""
    where = "the cage's region" if is_cage else "the lattice"
    if not is_cage and outside_modes.mode(info.outside_mode).has_distance:
        what = (f"the deformation fades out over {info.falloff:,} of them; "
                f"{info.beyond or 0:,} beyond the falloff distance stay where they are")
    else:
        what = ("they follow its boundary" if info.outside_follow else "they stay where they are")
        if not is_cage and info.outside_follow:
            what += ", as with the Lattice modifier"
    return f"{info.outside:,} of {info.n_verts:,} vertices lie outside {where} ({what})"


def forget_status(obj=None, key=None):
    """Drop the status of one deformer (`key`), of every deformer of `obj`, or of all."""
    for table in (_stats, _reported):
        if obj is None and key is None:
            table.clear()
        for k in [k for k in table if k == key or (obj is not None and k[0] == obj.session_uid)]:
            del table[k]
