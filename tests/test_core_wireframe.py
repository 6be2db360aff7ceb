"""What the overlay draws and the correction's inputs in lattice space, in the core
(`vpffd_addon/wireframe.py`, `cage_cells.py`, `lattice_space.py`): edges join exactly the
neighbouring points, the falloff box is the box the falloff's factor reaches zero on, the cells
survive their saved form, World directions and pin targets are the world's motions seen from the
lattice."""
import numpy as np
import pytest

import vpffd_addon as vp
from vpffd_addon import cage_cells, lattice_space, wireframe
from vpffd_addon.linalg3 import affine, affine_inverse

pytestmark = pytest.mark.core


@pytest.mark.parametrize("shape", [(2, 2, 2), (4, 3, 2), (5, 1, 1), (1, 1, 1), (3, 1, 4)])
def test_lattice_edges_join_each_pair_of_grid_neighbours_once(shape):
    lat = vp.Lattice(shape, bounds=((0,) * 3, (1,) * 3))
    # Blender's order (u fastest): point index -> its grid coordinates.
    ijk = np.stack(np.unravel_index(np.arange(np.prod(shape)), shape[::-1])[::-1], 1)
    expected = {(a, b) for a in range(len(ijk)) for b in range(a + 1, len(ijk))
                if np.abs(ijk[a] - ijk[b]).sum() == 1}
    edges = wireframe.lattice_edges(shape)
    assert edges.shape == (len(expected), 2)
    assert {tuple(sorted(e)) for e in edges.tolist()} == expected
    assert len(lat.rest_points) == np.prod(shape)


def test_cage_edges_are_the_faces_sides_once_and_the_cells_survive_their_saved_form():
    cage = vp.box_cage((2, 1, 1))
    edges = wireframe.cage_edges(cage.cells)
    assert len(edges) == 20 and len({tuple(e) for e in edges.tolist()}) == 20   # 12 + 12 - 4 shared
    assert (edges[:, 0] < edges[:, 1]).all()
    flat = cage_cells.encode_cells(cage.cells)
    assert all(isinstance(x, int) for x in flat)
    assert cage_cells.decode_cells(flat) == [tuple(tuple(f) for f in c) for c in cage.cells]
    for damaged in (flat[:-1], [], [3] + flat[1:]):
        with pytest.raises(ValueError, match="damaged"):
            cage_cells.decode_cells(damaged)


def test_falloff_box_is_where_the_falloff_reaches_zero():
    lat = vp.Lattice((3, 3, 3), bounds=((-1, 0, 2), (1, 3, 2.5)))
    corners = wireframe.falloff_box(lat, 0.4)
    for a, b in wireframe.BOX_EDGES:              # each edge runs along one axis
        assert np.count_nonzero(corners[a] != corners[b]) == 1
    centre = (lat.lo + lat.hi) / 2
    for k in range(3):   # just inside and just outside the box's face along each axis
        inside = centre.copy()
        inside[k] = corners[:, k].max() - 1e-6
        outside = centre.copy()
        outside[k] = corners[:, k].max() + 1e-6
        f = vp.outside_factor(lat, np.array([inside, outside]), "FALLOFF", 0.4)
        assert f[0] > 0 and f[1] == 0


def _rotation(angle, axis):
    c, s = np.cos(angle), np.sin(angle)
    i, j = [a for a in range(3) if a != axis]
    m = np.eye(4)
    m[i, i], m[i, j], m[j, i], m[j, j] = c, -s, s, c
    return m


def test_world_directions_are_the_world_axes_seen_from_the_lattice():
    M = _rotation(0.7, 2) @ np.diag([2.0, 0.5, 1.0, 1.0])
    M[:3, 3] = (1, 2, 3)
    assert lattice_space.directions("NONE", "WORLD", M) == ("", None)
    assert lattice_space.directions("XZ", "LATTICE", M) == ("XZ", None)
    axes, dirs = lattice_space.directions("XZ", "WORLD", M)
    assert axes == "" and dirs.shape == (2, 3)
    for d, world_axis in zip(dirs, (0, 2)):
        world = M[:3, :3] @ d                     # a lattice-space displacement seen in the world
        world /= np.linalg.norm(world)
        np.testing.assert_allclose(world, np.eye(3)[world_axis], atol=1e-12)


def test_pin_targets_carry_pinned_vertices_by_the_empty_s_motion():
    rng = np.random.default_rng(3)
    X = rng.normal(size=(10, 3))
    lat_M = _rotation(0.3, 0)
    lat_M[:3, 3] = (0.5, 0, 0)
    mesh_rest = _rotation(0.2, 1)
    empty_rest = np.eye(4)
    empty_now = _rotation(0.9, 2)
    empty_now[:3, 3] = (0, 0, 1)
    assert lattice_space.pin_targets([], X, lat_M, empty_now, empty_rest.ravel(), mesh_rest.ravel()) == []
    pins = np.array([2, 7])
    got = lattice_space.pin_targets(pins, X, lat_M, empty_now, empty_rest.ravel(), mesh_rest.ravel())
    assert [v for v, _ in got] == [2, 7]
    # Where the vertex was in the world at Bind, moved as the Empty moved, seen from the lattice.
    world = affine(X[pins], mesh_rest)
    moved = affine(world, empty_now @ np.linalg.inv(empty_rest))
    np.testing.assert_allclose(np.array([t for _, t in got]), affine(moved, affine_inverse(lat_M)),
                               atol=1e-12)
