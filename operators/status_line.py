"""The first line of VP-FFD's panel: what VP-FFD is doing to the object now, in one sentence and an
icon. The Status sub-panel gives the details (timings, warnings, figures of the plain lattice)."""

#: Bake > Use Live Solve: the panel and the button it names (tests check both exist).
LIVE_SOLVE_PATH = "Bake > Use Live Solve"


def reference_words(info):
    """What the volume figures of `info` (an `engine.Status`) are percentages of, in words."""
    if info.target_from == "bind":
        return "its volume at Bind"
    return "the mesh as edited" if info.editing else "its input"


def headline(info, bound, using_cache):
    """(text, icon name) for an object with `engine.Status` `info`; `bound`: whether it is bound;
    `using_cache`: whether a baked cache plays instead of the live solve."""
    if not bound:
        return "not bound: pick a Lattice (or a VP-FFD cage), then Bind", "INFO"
    if using_cache:
        return f"playing the baked cache ({LIVE_SOLVE_PATH} switches back)", "FILE_CACHE"
    if info.switched_off:
        return "switched off in the viewport", "HIDE_ON"
    if info.paused:
        return info.paused, "PAUSE"
    if info.error:
        return info.error, "ERROR"
    if info.volume_percent is None:
        if info.seconds is not None:
            return "deforming as the Lattice modifier does (Correction: None)", "CHECKMARK"
        return "waiting for the next update", "TIME"
    text = f"volume {info.volume_percent:.3f}% of {reference_words(info)}"
    if info.warnings:
        return text + f" ({len(info.warnings)} warning{'s' if len(info.warnings) > 1 else ''} "\
                      "in Status)", "ERROR"
    return text, "CHECKMARK"
