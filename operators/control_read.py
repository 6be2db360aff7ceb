"""Reads of the control object (a Lattice object or a VP-FFD cage) for a frame: its model at rest,
its evaluated points, its vertex groups, its world matrix. Safe in the lattice's Edit Mode."""
import numpy as np

from .. import vpffd_addon as vp
from ..vpffd_addon import cage_cells
from . import cage, meshio
from .saved_data import CAGE_REST_PROPERTY, saved


def is_control(ob):
    """Whether `ob` can deform a bound mesh: a Lattice object or a VP-FFD cage mesh."""
    return ob is not None and (ob.type == "LATTICE" or cage.is_cage(ob))


def missing_control(ob):
    """What is wrong with `ob` as the lattice setting (it is not `is_control`), in words."""
    if ob is not None and ob.type == "MESH":
        return (f"mesh '{ob.name}' is not a VP-FFD cage (it has no cells): make one with "
                "Add > VP-FFD Cage, or pick a Lattice object")
    return "the lattice is missing: pick a Lattice object or a VP-FFD cage, or Unbind"


def cage_points(cage_eval, n_points):
    """(N, 3) evaluated cage points (shape keys, hooks, armatures and modifiers applied)."""
    points = meshio.mesh_coords(cage_eval.data)
    if len(points) != n_points:
        # In Edit Mode the evaluated mesh wraps the edit mesh and lists no vertices: convert it.
        try:
            points = meshio.mesh_coords(cage_eval.to_mesh())
        finally:
            cage_eval.to_mesh_clear()
    if len(points) != n_points:
        raise ValueError(f"cage '{cage_eval.name}' evaluates to {len(points)} points instead of "
                         f"{n_points}: remove modifiers that add or remove its vertices")
    return points


def _cage_model(state, obj, cage_ob, helper):
    """(vp.Cage at bind time, its rest points (N, 3), key) for a bound deformer, cached in its state."""
    flat = tuple(cage_ob.data[cage.CELLS_PROPERTY].to_list())
    rest = saved(helper, obj, CAGE_REST_PROPERTY)
    if rest is None:
        raise ValueError("the mesh was bound to another kind of lattice: Re-bind")
    rest = np.array(rest.to_list(), np.float64).reshape(-1, 3)
    key = (hash(flat), rest.tobytes())
    if state.cage_key != key:
        cells = cage_cells.decode_cells(flat)
        if len(rest) != len(cage_ob.data.vertices):
            raise ValueError(f"cage '{cage_ob.name}' has {len(cage_ob.data.vertices)} points, "
                             f"{len(rest)} when bound: Re-bind")
        state.cage_model, state.cage_key = vp.Cage(rest, cells), key
    return state.cage_model, rest, ("cage", key[0])


# Lattice data read in Object Mode. In a lattice's Edit Mode, `LatticePoint.co` holds garbage and
# `LatticePoint.groups` reads out of bounds (it can crash Blender): there, the rest grid and the
# group weights come from the last Object Mode read (or from Bind), never from the points.
_lattice_reads = {}   # lattice data session_uid -> {"grid": (N, 3), "groups": {name: (N,)}}


def _lattice_entry(lat_ob):
    return _lattice_reads.setdefault(lat_ob.data.session_uid, {"grid": None, "groups": {}})


def _lattice_rest(lat_ob, s):
    """(vp.Lattice, rest grid (N, 3)) of a Lattice object; safe in the lattice's Edit Mode."""
    data = lat_ob.data
    shape = (data.points_u, data.points_v, data.points_w)
    interp = (data.interpolation_type_u, data.interpolation_type_v, data.interpolation_type_w)
    entry = _lattice_entry(lat_ob)
    if not data.is_editmode:
        entry["grid"] = meshio.lattice_points(data, "co")
    grid = entry["grid"]
    if grid is None or len(grid) != len(data.points):
        lattice = vp.Lattice(shape, interp, bounds=(s.lattice_rest_lo, s.lattice_rest_hi))  # Bind's
        return lattice, lattice.rest_points
    lo, hi = grid.min(0), grid.max(0)
    key = (shape, interp, lo.tobytes(), hi.tobytes())
    if entry.get("lattice_key") != key:
        # (kept while unchanged: a lattice makes its rest grid once, and a frame asks for it)
        entry["lattice"], entry["lattice_key"] = vp.Lattice(shape, interp, bounds=(lo, hi)), key
    return entry["lattice"], grid


def _lattice_group(lat_ob, name):
    """(N,) weights of vertex group `name` of the lattice or cage, or raise ValueError. Read in
    Object Mode only (see `_lattice_reads`)."""
    if lat_ob.type != "LATTICE":
        return meshio.lattice_group_weights(lat_ob, name)
    entry = _lattice_entry(lat_ob)
    if not lat_ob.data.is_editmode:
        weights = meshio.lattice_group_weights(lat_ob, name)
        entry["groups"][name] = weights
        return weights
    weights = entry["groups"].get(name)
    if weights is None or len(weights) != len(lat_ob.data.points):
        raise ValueError(f"the weights of vertex group '{name}' are read in Object Mode: leave the "
                         "lattice's Edit Mode once")
    return weights


def _lattice_weights(lat_ob):
    """(N,) weights of the lattice's own vertex group (Lattice > Vertex Group), or None."""
    if lat_ob.type != "LATTICE" or not lat_ob.data.vertex_group:
        return None
    if lat_ob.vertex_groups.get(lat_ob.data.vertex_group) is None:
        return None              # a name the lattice lacks: Blender's modifier ignores it too
    return _lattice_group(lat_ob, lat_ob.data.vertex_group)


def mobility_of(s, lattice_object):
    """(N,) mobility from a vertex group of the lattice or cage, or None."""
    if not s.mobility_group:
        return None
    return _lattice_group(lattice_object, s.mobility_group)


def control_inputs(obj, state, s, lat_ob, depsgraph, helper):
    """(lattice or cage model, rest grid (N, 3), points now (N, 3), the lattice's own weights
    (N,) or None, (depth, outside) of a cage or None, the control object's world matrix)."""
    lat_eval = lat_ob.evaluated_get(depsgraph)
    if lat_ob.type == "LATTICE":
        lattice, grid = _lattice_rest(lat_ob, s)
        points = meshio.lattice_points(lat_eval.data, "co_deform")
        weights, cage_options = _lattice_weights(lat_ob), None
    else:
        lattice, grid, _ = _cage_model(state, obj, lat_ob, helper)
        points = cage_points(lat_eval, lattice.n_points)
        weights, cage_options = None, (s.cage_depth, s.cage_outside)
    if len(points) != lattice.n_points:
        raise ValueError(f"lattice '{lat_ob.name}' has {len(points)} points, expected {lattice.n_points}")
    return lattice, grid, points, weights, cage_options, meshio.matrix(lat_eval.matrix_world)
