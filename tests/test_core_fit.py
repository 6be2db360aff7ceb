"""vpffd_addon.fit_lattice: the lattice that "VP-FFD Lattice Deform Selected" fits around meshes."""
import numpy as np
import pytest

import vpffd_addon as vp

pytestmark = pytest.mark.core


def test_the_box_holds_every_point_with_the_margin_and_cells_about_square():
    rng = np.random.default_rng(1)
    pts = rng.uniform((-1.0, -0.5, 2.0), (3.0, 0.5, 2.8), (500, 3))   # 4 x 1 x 0.8
    centre, size, shape = vp.fit_lattice(pts, margin=0.05, resolution=5)
    lo, hi = pts.min(0), pts.max(0)
    np.testing.assert_allclose(centre, 0.5 * (lo + hi))
    np.testing.assert_allclose(size, (hi - lo) + 2 * 0.05 * (hi - lo).max())
    assert (centre - 0.5 * size < lo - 0.19).all() and (centre + 0.5 * size > hi + 0.19).all()
    assert shape.tolist() == [5, 2, 2]                 # 4.4 : 1.4 : 1.2 of 5 points, at least 2
    cells = size / (shape - 1)
    assert cells.max() / cells.min() < 1.5


def test_flat_and_single_point_inputs_still_get_a_box():
    flat = np.array([[0, 0, 0], [1, 0, 0], [0, 2, 0], [1, 2, 0]], float)
    centre, size, shape = vp.fit_lattice(flat, margin=0.0, resolution=4)
    assert size[2] > 0 and shape[2] == 2 and shape[1] == 4
    centre, size, shape = vp.fit_lattice([[1.0, 2.0, 3.0]])
    np.testing.assert_allclose(centre, (1, 2, 3))
    assert (size > 0).all() and shape.tolist() == [4, 4, 4]


@pytest.mark.parametrize("bad, match", [(np.zeros((0, 3)), "no points"),
                                        ([[0.0, np.nan, 0.0]], "finite")])
def test_bad_input_is_refused_in_words(bad, match):
    with pytest.raises(ValueError, match=match):
        vp.fit_lattice(bad)
    with pytest.raises(ValueError, match="resolution"):
        vp.fit_lattice([[0.0, 0.0, 0.0]], resolution=1)
