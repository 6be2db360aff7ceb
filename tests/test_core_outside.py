"""The table of Outside modes (`vpffd_addon/outside.py`): every mode is listed once, its settings'
items are numbered as files stored them, an earlier name reads the mode under its name now, and
each mode's factor is what the frame applies (a vertex outside moves, fades or stays)."""
import numpy as np
import pytest

import vpffd_addon as vp
from vpffd_addon import outside

pytestmark = pytest.mark.core


def test_every_name_is_one_mode_and_unknown_names_say_the_choices():
    seen = [n for m in outside.MODES for n in (m.name,) + m.aliases]
    assert len(seen) == len(set(seen))
    assert outside.mode("inside") is outside.mode("STAY")
    assert outside.mode("STAY", "cage") is outside.mode("STAY")
    with pytest.raises(ValueError, match="FOLLOW, STAY"):
        outside.mode("FALLOFF", "cage")         # a cage's region is not a box
    with pytest.raises(ValueError, match="FOLLOW, FALLOFF, STAY"):
        outside.mode("NOWHERE")


def test_enum_numbers_are_the_ones_files_stored():
    # Files store the number: the lattice's FOLLOW 0, FALLOFF 1, INSIDE (now STAY) 2; the
    # cage's FOLLOW 0, STAY 1. An earlier name shares its mode's number.
    lattice = {ident: number for ident, _, _, number in outside.enum_items("lattice")}
    cage = {ident: number for ident, _, _, number in outside.enum_items("cage")}
    assert lattice == {"FOLLOW": 0, "FALLOFF": 1, "STAY": 2, "INSIDE": 2}
    assert cage == {"FOLLOW": 0, "STAY": 1, "INSIDE": 1}
    assert [i[0] for i in outside.enum_items("lattice")][:3] == list(outside.names("lattice"))


@pytest.mark.parametrize("m", outside.MODES, ids=lambda m: m.name)
def test_each_modes_factor_moves_fades_or_keeps_outside_vertices(m):
    lat = vp.Lattice((3, 3, 3), bounds=((-1,) * 3, (1,) * 3))
    v = np.array([[0.0, 0, 0], [1.0, 0, 0], [1.2, 0, 0], [3.0, 0, 0]])
    f = vp.outside_factor(lat, v, m.name, 0.5)
    assert f.shape == (4,) and f[0] == 1 and f[1] == 1        # inside, and on the box's face
    if m.follows:
        assert (f == 1).all()
    elif m.has_distance:
        assert 0 < f[2] < 1 and f[3] == 0                      # 0.1 sizes out: fading; 1: gone
    else:
        assert f[2] == 0 and f[3] == 0
    for alias in m.aliases:
        np.testing.assert_array_equal(vp.outside_factor(lat, v, alias, 0.5), f)


def test_a_cage_binds_with_each_of_its_modes_and_an_earlier_name():
    cage = vp.box_cage((1, 1, 1))
    v, t = vp.icosphere(1, 1.5)                                # partly outside the cage
    moved = cage.rest_points * 1.2
    for name in outside.names("cage") + ("inside",):
        m = outside.mode(name, "cage")
        b = vp.bind(cage, v, t, depth=0, outside=name)
        assert b.outside == m.name and b.n_outside > 0
        out = b.solve(moved, axes="", preserve_volume=False).verts
        far = np.abs(v).max(1) > 1 + 1e-6
        assert (np.abs(out[far] - v[far]).max() > 1e-3) == m.follows
