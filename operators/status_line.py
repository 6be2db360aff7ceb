"""The first line of VP-FFD's panel: what VP-FFD is doing to the object now, in one sentence and an
icon; and the lines of the Status sub-panel, the details (timings, warnings, figures of the plain
lattice). Words only: the panel draws them, tests read them."""
from .text import count, percent

#: Bake > Use Live Solve: the panel and the button it names (tests check both exist).
LIVE_SOLVE_PATH = "Bake > Use Live Solve"


def reference_words(info):
    """What the volume figures of `info` (an `status.Status`) are percentages of, in words."""
    if info.target_from == "bind":
        return "its volume at Bind"
    return "the mesh as edited" if info.editing else "its input"


def problems(info):
    """The warnings of `info` that the Status sub-panel lists, each once, in its order: the first
    line counts these."""
    found = [f"the lattice folds space: {count(info.folds)} inverted vertices"] if info.folds else []
    return found + list(dict.fromkeys(info.warnings))


def applied_lattice(settings):
    """The name of the lattice in an unbound mesh's Lattice field whose deformation Apply made the
    mesh's own shape (Bind would deform it again), or None."""
    lat = settings.lattice
    if settings.is_bound or lat is None or settings.applied_lattice != lat.name:
        return None
    return lat.name


def headline(info, bound, using_cache, applied=None, kernels="ready"):
    """(text, icon name) for an object with `status.Status` `info`; `bound`: whether it is bound;
    `using_cache`: whether a baked cache plays instead of the live solve; `applied`: the
    `applied_lattice` of an unbound mesh; `kernels`: the compiled kernels' state
    (`compiled_backend.status()[0]`)."""
    if not bound:
        if applied:
            return (f"applied: this shape is now the mesh's own. Bind would deform it again by "
                    f"'{applied}' as it is now (put the lattice back to its rest shape first, or "
                    "pick another)"), "INFO"
        return "not bound: pick a Lattice (or a VP-FFD cage), then Bind", "INFO"
    if using_cache:
        return f"playing the baked cache ({LIVE_SOLVE_PATH} switches back)", "FILE_CACHE"
    if info.switched_off:
        return "switched off in the viewport", "HIDE_ON"
    if info.paused:
        return info.paused, "PAUSE"
    if info.error:
        return info.error, "ERROR"
    if info.seconds is None:
        return "waiting for the next update", "TIME"
    warned = problems(info)
    if info.volume_percent is not None:
        text = f"volume {percent(info.volume_percent)} of {reference_words(info)}"
    elif info.encloses_nothing:
        text = ("the mesh is open and encloses no volume: the lattice deforms it as the Lattice "
                "modifier does, whatever the Correction")
    else:
        text = "deforming as the Lattice modifier does"
    if warned:
        return text + f" ({len(warned)} warning{'s' if len(warned) > 1 else ''} in Status)", "ERROR"
    if kernels == "compiling" and info.awaits_kernels:      # the live state: not once compiled
        return ("compiling VP-FFD's kernels (first use only): solving with NumPy meanwhile, "
                + text), "TIME"
    return text, "CHECKMARK" if info.volume_percent is not None else "INFO"


def status_lines(info, using_cache, backend):
    """[(text, icon name)] of the Status sub-panel for `status.Status` `info`; `using_cache`:
    whether a baked cache plays; `backend`: the Backend setting. Every warning the first line
    counts is listed once, with the ERROR icon; nothing else has that icon."""
    if using_cache:
        return [(f"playing the baked cache: VP-FFD is not solving ({LIVE_SOLVE_PATH} switches back)",
                 "FILE_CACHE")]
    if info.switched_off:
        return [("the VP-FFD modifier is switched off in the viewport", "HIDE_ON")]
    if info.paused:
        return [(info.paused, "PAUSE")]
    out = [(info.error, "ERROR")] if info.error else []
    if info.editing:
        out.append(("Edit Mode: solved live from the mesh as edited", "EDITMODE_HLT"))
    warned = problems(info)
    if info.volume_percent is not None and info.plain_percent != info.volume_percent:
        # The volume itself is on the first line; here what the plain lattice gives, where it
        # differs. A check mark only where nothing went wrong (never beside a missed target).
        out.append((f"the plain Lattice modifier would give {percent(info.plain_percent)} of "
                    f"{reference_words(info)}", "INFO" if warned else "CHECKMARK"))
    if info.seconds is not None:
        kernels = f" ({info.kernels} kernels)" if info.kernels else ""
        out.append((f"solved in {1e3 * info.seconds:.1f} ms on the {info.backend}{kernels}, "
                    f"{count(info.n_verts)} vertices", "TIME"))
    if info.kernels == "NumPy" and info.kernels_why:
        out.append((info.kernels_why, "INFO"))
    if info.backend_reason and backend != "CPU":
        out.append((info.backend_reason, "INFO"))
    if info.closed is False:
        out.append((open_mesh_words(info), "INFO"))
    # Vertices outside the lattice: in the Outside (or Cage) sub-panel, beside the setting.
    return out + [(text, "ERROR") for text in warned]


def open_mesh_words(info):
    """Words for an open mesh (`info.closed` False): what its volume is and what VP-FFD keeps."""
    if info.encloses_nothing:
        return ("the mesh is open and encloses no volume about the lattice's centre: the lattice "
                "deforms it as the Lattice modifier does, whatever the Correction")
    return "the mesh is not closed: the volume of an open surface is measured about the lattice centre"
