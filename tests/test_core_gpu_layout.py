"""The GPU path's data layout, built in the core and checked here without Blender: the one-ring
gather gives the binding's volume gradient and the per-control-point sums of pieces give its
transposed product, on meshes with several islands and blocks."""
import numpy as np
import pytest

import vpffd_addon as vp
from vpffd_addon.gpu_layout import gpu_layout, gradient_by_ring, transpose_by_pieces

pytestmark = pytest.mark.core


@pytest.mark.parametrize("shape", [(4, 4, 4), (3, 5, 2)])
def test_the_layout_reproduces_gradient_and_transpose(shape):
    v1, f1 = vp.icosphere(3, 0.3, (-0.2, 0.0, 0.0))
    v2, f2 = vp.box(4, 0.3)
    v = np.vstack([v1, v2 + (0.25, 0.05, 0.0)])
    f = np.vstack([f1, f2 + len(v1)])
    lat = vp.Lattice(shape, "BSPLINE", bounds=((-0.6,) * 3, (0.6,) * 3))
    b = vp.bind(lat, v, f, influence=np.linspace(0.2, 1.0, len(v)))
    layout = gpu_layout(b)
    assert len(layout["ring_start"]) == b.x0.shape[1] + 1 and len(layout["slot"]) == len(v)
    rng = np.random.default_rng(1)
    X = b.x0 + rng.normal(0, 0.01, b.x0.shape)
    for a in range(3):
        a1, a2 = (a + 1) % 3, (a + 2) % 3
        g = b._gradient_of(X[a1], X[a2])
        np.testing.assert_allclose(gradient_by_ring(layout, X[a1], X[a2]), g, atol=1e-12)
        Kw, Kuv = b.ww.shape[1], b.wuv.shape[1]
        np.testing.assert_allclose(transpose_by_pieces(layout, g, Kw, Kuv, b.block_size),
                                   b._transpose(g), atol=1e-10)


def test_cage_bindings_have_no_gpu_layout():
    cage = vp.box_cage((1, 1, 1), ((-1,) * 3, (1,) * 3))
    v, f = vp.icosphere(1, 0.5)
    with pytest.raises(ValueError, match="Lattice bindings"):
        gpu_layout(vp.bind(cage, v, f, depth=0))
