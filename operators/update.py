"""The update of bound deformers, from the depsgraph handler (`update_scene`) or an operator
(`update`): read what Blender hands over (`frame_read.read`), evaluate the core's pipeline on it
(`_evaluate`), publish the result (`publish.publish`). Never raises into Blender."""
import dataclasses
import time

import numpy as np

from . import compiled_backend, deformers, node_group, tracked_objects
from .bound import Bound, states
from .frame_read import read
from .publish import count_folds, encloses_nothing, publish, zero_offsets
from .release import release
from .status import deformer_of, set_status, status


def update(target, depsgraph, force=False):
    """Solve the current frame for bound deformer `target` (a `deformers.Deformer`, or a mesh
    object for its first deformer) and write its offsets. Never raises: problems go to the panel
    (`status(target).error`) and the console. Returns True when a solve ran. `force` solves even
    when the inputs did not change and the modifier is switched off (Bind, Apply, Check Folds and
    Bake need the solve)."""
    # Overflow is detected on the results and reported in words; NumPy's own warnings would only
    # repeat it on the console for every frame.
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        return _update(deformer_of(target), depsgraph, force)


def _update(d, depsgraph, force, helpers_taken=None):
    """One update of deformer `d` in three steps: read what Blender hands over (`read`), evaluate
    the core's pipeline on it (`_evaluate`), publish the result: offsets, panel figures, overlay
    (`publish`)."""
    state = None
    try:
        mod = _slot_to_solve(d, depsgraph, force)
        if mod is None:
            return False
        state = states.get(d.key)
        if state is None:
            state = states[d.key] = Bound()
        state.wrote = False
        frame = read(d, state, depsgraph, helpers_taken)
        if frame is None or (not force and _unchanged(state, frame)):
            return False
        t0 = time.perf_counter()
        result = _evaluate(state, frame)
        publish(d, state, frame, result, t0)
        return True
    except Exception as exc:  # a handler must never raise into Blender
        try:
            zero_offsets(d, state)   # a defined result: the slot's input, undeformed
        except Exception:
            pass
        if state is not None:
            state.signature = None
        set_status(d, error=f"{type(exc).__name__}: {exc}" if not isinstance(exc, ValueError) else str(exc))
        return False


def update_object(obj, depsgraph, force=False, helpers_taken=None):
    """Update every bound deformer of `obj`, in stack order. New offsets of one change what
    reaches the VP-FFD modifiers after it (and a changed input, e.g. Tap Faces, leaves the object
    to be evaluated), so the object is evaluated again before those read their input: a frame's result never waits for a later handler call (a render calls the frame
    handler once). Returns True when a solve ran."""
    if depsgraph.mode != "RENDER" and len(obj.modifiers) > 1 and _adopt_copies(obj):
        return False        # the copy's tap is its own from the next evaluation on
    solved = False
    found = deformers.bound(obj)
    for k, d in enumerate(found):
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            solved |= _update(d, depsgraph, force, helpers_taken)
        state = states.get(d.key)
        inputs_changed = obj.session_uid in node_group.retagged
        node_group.retagged.discard(obj.session_uid)
        if (inputs_changed or (state is not None and state.wrote)) \
                and any(later.mod is not None for later in found[k + 1:]):
            depsgraph.update()
    return solved


def update_scene(scene, depsgraph):
    """Update every bound object of `scene`, and those linked from a library that `depsgraph`
    shows through collection instances (`tracked_objects`)."""
    taken = set()   # each modifier gets a solver helper of its own (duplicates share one)
    for ob in tracked_objects.bound_objects(scene, depsgraph):
        update_object(ob, depsgraph, False, taken)


def _adopt_copies(obj):
    """Give a VP-FFD modifier that no settings name (a copy of another, made in the stack with
    Duplicate or Copy to Selected) settings of its own, copied from the deformer it was copied
    from but not bound, its own slot and no offsets (it would add those of the helper it shares):
    it deforms nothing until it is bound, and its panel offers Bind. Returns True when a
    modifier changed (the object then waits for its next evaluation)."""
    if obj.library is not None:
        return False
    mods = deformers.modifier.find_all(obj)
    changed = False
    for m in mods:
        if deformers.settings_of(obj, m, mods) is None:
            solver = node_group.get_input(m, node_group.SOLVER_INPUT)
            source = next((d for d in deformers.all_of(obj) if d.mod is not None and d.mod != m
                           and node_group.get_input(d.mod, node_group.SOLVER_INPUT) == solver), None)
            s = deformers.claim(obj, m)
            if source is not None:
                deformers.copy_settings(source.settings, s)
            node_group.set_input(m, node_group.SOLVER_INPUT, None)
            deformers.modifier.sync_inputs(m, s)
            changed = True
    return changed


def request_update(obj):
    """Settings changed: have the next depsgraph update recompute this object."""
    if getattr(obj, "type", None) == "MESH" and deformers.is_bound(obj):
        obj.update_tag(refresh={"DATA"})    # not a plain tag: see node_group.set_input


# ---------------------------------------------------------------------------------------- bind


def _linked_without_override(d):
    """Deformer `d`'s object is linked from a library with no library override (a collection
    instance of a rig, say): linked data is read-only, so nothing VP-FFD solves can reach it, and
    Blender shows what its solver helper held when the library was saved. Said in the panel and,
    once, in the console (`set_status`); nothing is written."""
    obj = d.obj
    why = (f"'{obj.name}' is linked from {obj.library.filepath} without a library override: linked data is "
           "read-only, so VP-FFD cannot write its shape and Blender shows the shape saved with "
           "the library on every frame. Make a library override of it, or bake a point cache in "
           "the library (Bake to Point Cache), which Blender's Mesh Cache modifier plays everywhere")
    set_status(d, error=why)


def _evaluated_here(obj, depsgraph):
    """Whether `depsgraph` evaluates `obj` at all: visible in its view layer (the viewport), or
    enabled for renders (a render evaluates what renders)."""
    try:
        if depsgraph.mode == "RENDER":
            return _renders(obj, depsgraph.view_layer)
        return bool(obj.visible_get(view_layer=depsgraph.view_layer))
    except (ReferenceError, RuntimeError, TypeError):
        return True


def _renders(obj, view_layer):
    """Whether a render of `view_layer` renders `obj`: not hidden from renders itself, and in a
    collection that is neither excluded from the view layer nor hidden from renders, nor below
    one that is."""
    if obj.hide_render:
        return False
    stack = [view_layer.layer_collection]
    while stack:
        layer_collection = stack.pop()
        if layer_collection.exclude or layer_collection.collection.hide_render:
            continue
        if layer_collection.collection.objects.get(obj.name) == obj:
            return True
        stack.extend(layer_collection.children)
    return False


def _slot_to_solve(d, depsgraph, force):
    """The VP-FFD modifier of deformer `d` when this evaluation should solve it; else None, with
    the panel told why (removed, switched off, hidden)."""
    if not d.settings.is_bound:
        return None
    obj, mod = d.obj, d.mod
    rendering = depsgraph.mode == "RENDER"
    if obj.library is not None:
        # Linked, no override. A rig baked in its library plays its cache there (its VP-FFD
        # modifiers switched off): nothing to say.
        if mod is not None and (mod.show_render if rendering else mod.show_viewport):
            _linked_without_override(d)
        return None
    if mod is None:
        if not rendering:
            # Removed (X on the modifier) or applied (Ctrl+A): as with any modifier, the object
            # is no longer deformed by it. Its settings stay for a later Bind.
            release(d)
        return None
    if not force and not (mod.show_render if rendering else mod.show_viewport):
        if not rendering:
            # Switched off in the viewport: the panel says so instead of an error or figures of
            # an earlier solve; switching it on solves again.
            _pause(d, switched_off=True)
        return None  # switched off for this evaluation, like any modifier
    if not force and not _evaluated_here(obj, depsgraph):
        # Hidden (H, Disable in Viewports, a hidden or excluded collection): Blender does not
        # evaluate it, so nothing reaches the slot. Keep the offsets shown last and solve again
        # when it is shown: it comes back as it was, with no error.
        if not rendering:
            _pause(d, paused="the object is hidden: VP-FFD solves again when it is shown")
        return None
    return mod


def _pause(d, **why):
    """Nothing is solved now (`why`: paused=text or switched_off=True): the panel shows no
    figures, since they would be those of another state; the next update solves again."""
    set_status(d, **why)
    state = states.get(d.key)
    if state is not None:
        state.signature = None


def _unchanged(state, frame):
    """Whether `frame` has the inputs of the last solve (its result is already shown)."""
    return frame.signature.matches(state.signature)


def _evaluate(state, frame):
    """The core's pipeline on `frame` (its solver picks the CPU or the GPU; on the CPU, the
    compiled kernels once they are loaded): a vp.FrameResult.

    An open surface with no volume about the lattice's centre (a plane through it) has no volume
    to keep: aiming at zero would bend it into another shape. It deforms as the Lattice modifier
    does (pins still hold). Such a mesh stays so from frame to frame, so once found the plain
    deformation is tried first and the correction only when the mesh no longer is one."""
    if state.settings.backend != "NUMPY":
        compiled_backend.start()    # once per session; NumPy solves until the kernels are ready
    inputs = frame.inputs
    plain = dataclasses.replace(inputs, axes="", directions=None, correct=bool(inputs.pins))
    state.backend = ("CPU", "")
    if inputs.correct and state.encloses_nothing:
        result = state.pipeline.evaluate(plain)
        if encloses_nothing(result):
            return result
        state.backend = ("CPU", "")
    result = state.pipeline.evaluate(inputs)
    state.encloses_nothing = inputs.correct and encloses_nothing(result)
    if state.encloses_nothing:
        state.backend = ("CPU", "")
        result = state.pipeline.evaluate(plain)
    return result


def check_folds(target, depsgraph):
    """Solve the current frame of deformer `target` and count folds whatever the mesh size;
    None on error."""
    d = deformer_of(target)
    if not update(d, depsgraph, force=True) and status(d).error:
        return None
    state = states.get(d.key)
    if state is None or state.result is None or state.result.binding is None:
        return None
    info = status(d)
    info.folds = count_folds(state.result.binding, state.result.points, state.orientation)
    return info.folds


def slot_output(target):
    """(V, 3) float32 positions the slot of deformer `target` gave in the last solve (object
    space), or None."""
    state = states.get(deformer_of(target).key)
    return None if state is None else state.output
