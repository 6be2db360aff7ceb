"""The GPU path's data layout, built in the core and checked here without Blender: what its
kernels compute from it, written out in NumPy below, is the binding's own volume gradient (the
one-ring gather) and transposed product (the per-control-point sums of pieces), on meshes with
several islands and blocks."""
import numpy as np
import pytest

import vpffd_addon as vp
from vpffd_addon.gpu_layout import gpu_layout

pytestmark = pytest.mark.core


# What the GPU's kernels compute from the layout, written out in NumPy.

def gradient_by_ring(layout, xp, xq):
    """The gradient the GPU's one-ring gather computes, in NumPy: (n_slots,) from the slot
    coordinates xp, xq (n_slots,) on the two axes that complete the gradient's axis."""
    ring, start = layout["ring"], layout["ring_start"]
    m, n = ring[:, 0], ring[:, 1]
    terms = xp[m] * xq[n] - xq[m] * xp[n]
    sums = np.add.reduceat(np.r_[terms, 0.0], np.minimum(start[:-1], len(terms)))
    sums[start[:-1] == start[1:]] = 0.0
    return sums / 6.0


def transpose_by_pieces(layout, g, kw, kuv, block_size):
    """The transposed product the GPU's pieces and alpha kernels compute, in NumPy: (N,)."""
    n_slots = len(layout["s"])
    n_blocks = n_slots // block_size
    wuv = layout["wuv"].reshape(n_blocks, block_size, kuv)
    ww = layout["ww"].reshape(n_blocks, block_size, kw)
    gb = np.asarray(g, np.float64).reshape(n_blocks, block_size)
    pieces = np.einsum("bsw,bsk,bs->bwk", ww, wuv, gb).reshape(-1)
    order, start = layout["cp_piece"], layout["cp_start"]
    ordered = pieces[order]
    sums = np.add.reduceat(np.r_[ordered, 0.0], np.minimum(start[:-1], len(ordered)))
    sums[start[:-1] == start[1:]] = 0.0
    return sums


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
        g = b.gradient_of(X[a1], X[a2])
        np.testing.assert_allclose(gradient_by_ring(layout, X[a1], X[a2]), g, atol=1e-12)
        Kw, Kuv = b.ww.shape[1], b.wuv.shape[1]
        np.testing.assert_allclose(transpose_by_pieces(layout, g, Kw, Kuv, b.block_size),
                                   b.transpose(g), atol=1e-10)


def test_cage_bindings_have_no_gpu_layout():
    cage = vp.box_cage((1, 1, 1), ((-1,) * 3, (1,) * 3))
    v, f = vp.icosphere(1, 0.5)
    with pytest.raises(ValueError, match="Lattice bindings"):
        gpu_layout(vp.bind(cage, v, f, depth=0))
