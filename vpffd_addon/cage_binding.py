"""Binding a mesh to a `Cage`: B = S_embed R, R the refinement chain, S_embed at most 8 refined
points per vertex. Per frame the cage points are refined once (a few sparse products on the
refined lattice, independent of the mesh), then every vertex gathers its 8 refined points; the
transposed product runs the same way back. Both cost O(V + refined points).
"""
import numpy as np

from .binding import BindingBase, finish, prepare
from .cage import Cage
from .cells import TET_DW
from .embedding import (Elements, barycentric_weights, locate, nearest_boundary,
                        trilinear)
from .linalg3 import det3, solve3
from .outside import mode as outside_mode

_ROW_CHUNK = 256
_DENSE_MAX_ENTRIES = 8_000_000   # n_ext x N; 32 MB in float32


class CageBinding(BindingBase):
    """A mesh bound to a `Cage`; made by `bind(cage, ...)`. Coordinates are in the cage's space.

    Extra public attributes: `depth`, `refinement` (`subdivision.Refinement`), `n_outside`
    (vertices outside the region), `outside` ("FOLLOW" or "STAY").
    """

    @property
    def slot_island(self):
        return self._slot_island

    def _extended(self, d):
        """Cage-point values d (N,) or (N, k) -> values at the extended refined points."""
        if self.dense is not None:
            return self.dense @ np.asarray(d, self.dense.dtype)
        return self.elements.ext.matvec(self.refinement.apply(d))

    def _extended_transpose(self, z):
        """The transpose of `_extended`: (n_ext,) or (n_ext, k) -> (N,) or (N, k)."""
        if self.dense is not None:
            return self.dense.T @ np.asarray(z, self.dense.dtype)
        return self.refinement.apply_transpose(self.elements.ext.rmatvec(z))

    def forward(self, d):
        """(S B d) at every slot for a scalar field d (N,) on the cage points: (n_slots,) in the
        binding's dtype."""
        y = self._extended(np.asarray(d, np.float64)).astype(self.dtype)
        # Vertices of one run share their 8 refined points: gather once per run, then repeat.
        Y = np.repeat(y[self.run_corners], self.run_len, axis=0)
        return np.einsum("sk,sk->s", self.tw, Y)

    def _run_sums(self, g):
        """(n_runs, 8) per-run sums of the weights times g (n_slots,)."""
        return np.add.reduceat(self.tw * np.asarray(g, self.dtype)[:, None], self.run_start, axis=0)

    def transpose(self, g):
        """(S B)^T g for g (n_slots,): (N,) float, in the binding's dtype where the refinement is one
        dense matrix (`dense`), else float64."""
        z = np.bincount(self.run_corners.ravel(), self._run_sums(g).ravel(), self.n_ext)
        return self._extended_transpose(z)

    def island_transpose(self, g, k):
        """(S B)^T g for g (n_slots,) restricted to each island's slots (islands 0..k-1): (k, N)
        float, one row per island (dtype as `transpose`)."""
        keys = (self.run_island[:, None] * self.n_ext + self.run_corners).ravel()
        z = np.bincount(keys, self._run_sums(g).ravel(), k * self.n_ext)
        return self._extended_transpose(z.reshape(k, self.n_ext).T).T

    def rows(self, slots):
        """Rows of S B for the given vertex slots (k,) int: dense (k, N) float64."""
        slots = np.asarray(slots, np.int64)
        out = np.zeros((len(slots), self.lattice.n_points))
        for s in range(0, len(slots), _ROW_CHUNK):
            part = slots[s:s + _ROW_CHUNK]
            z = np.zeros((len(part), self.n_ext))
            np.add.at(z, (np.arange(len(part))[:, None], self.tidx[part]), self.tw[part].astype(np.float64))
            out[s:s + len(part)] = self._extended_transpose(z.T).T
        return out

    def jacobian_det(self, points):
        """det(d x' / d x) at every vertex for cage points `points` (N, 3): (V,) float64. The map
        is trilinear or affine inside each refined element; outside the region it is a
        translation (determinant 1)."""
        D = self.displacements(points)
        X = self._extended(self.lattice.rest_points)
        Y = X + self._extended(D)
        idx = self.tidx
        dw = np.where(self.is_hex[:, None, None], trilinear(self.param)[1], TET_DW[None])
        J0 = np.einsum("ska,skc->sca", dw, X[idx])
        J1 = np.einsum("ska,skc->sca", dw, Y[idx])
        inside = self.elem >= 0
        M = np.broadcast_to(np.eye(3), J0.shape).copy()
        M[inside] = solve3(J0[inside].transpose(0, 2, 1), J1[inside].transpose(0, 2, 1)).transpose(0, 2, 1)
        s = self.slot_influence.astype(np.float64)[:, None, None]
        det = det3(np.eye(3) + s * (M - np.eye(3)))
        if not np.isfinite(det).all():
            raise ValueError("the Jacobian overflows: the displacements are too large for the cage's cells")
        return det[self.slot]


def bind_cage(cage, rest_verts, tris, influence=None, dtype=np.float64, depth=3, outside="FOLLOW",
              topology=None):
    """Bind a triangle mesh to `cage` refined `depth` times. See `vpffd_addon.bind`."""
    if not isinstance(cage, Cage):
        raise ValueError(f"bind_cage needs a vpffd_addon.Cage, got {type(cage).__name__}")
    mode = outside_mode(outside, "cage").name      # the Outside modes' table (outside.py)
    b = CageBinding()
    verts, tris, s, labels, rel = prepare(b, cage, rest_verts, tris, influence, dtype, topology)
    V = b.n_verts
    b.depth, b.outside = int(depth), mode
    b.refinement = ref = cage.region(depth)
    b.elements = el = Elements(cage, ref)
    X = el.ext.matvec(ref.points)
    b.n_ext = len(X)
    # Small cages: the whole chain as one dense (n_ext, N) matrix, a single product per frame
    # instead of one sparse pass per level (the deep levels dominate); large ones keep the chain.
    b.dense = None
    if b.n_ext * cage.n_points <= _DENSE_MAX_ENTRIES:
        b.dense = np.ascontiguousarray(el.ext.matvec(ref.apply(np.eye(cage.n_points))), dtype=b.dtype)
    elem, param = locate(verts, X, el)
    out = np.flatnonzero(elem < 0)
    b.n_outside = len(out)
    weights = np.zeros((V, 8))
    corners = np.zeros((V, 8), np.int64)
    if len(out) and mode == "FOLLOW":
        # Outside the region a point moves with the nearest point of the region's boundary.
        near, near_param = nearest_boundary(verts[out], X, el)
        carried = np.zeros(V, bool)
        carried[out] = True
        src = np.where(elem >= 0, elem, 0)
        src[out] = near
        prm = param.copy()
        prm[out] = near_param
        elem_for_weights, param_for_weights, valid = src, prm, np.ones(V, bool)
    else:
        elem_for_weights, param_for_weights, valid = np.where(elem >= 0, elem, 0), param, elem >= 0
    hexes = el.is_hex[elem_for_weights]
    w = np.where(hexes[:, None], trilinear(param_for_weights)[0], barycentric_weights(param_for_weights))
    weights[valid] = w[valid]
    corners[valid] = el.corners[elem_for_weights[valid]]
    corners[~hexes & valid, 4:] = corners[~hexes & valid, :1]   # unused slots point somewhere valid

    # Slots: vertices sorted by (island, element), no padding.
    order = np.lexsort((elem_for_weights, labels))
    slot = np.empty(V, np.int64)
    slot[order] = np.arange(V)
    b.slot = slot
    b._slot_island = labels[order]
    b.slot_influence = s[order].astype(b.dtype)
    b.tidx = corners[order]
    b.tw = (weights[order] * s[order, None]).astype(b.dtype)
    b.param = param_for_weights[order]
    b.is_hex = hexes[order]
    b.elem = np.where(elem >= 0, elem, -1)[order]       # -1: outside (a translation)
    # Runs: consecutive slots of one island that share the same refined points.
    key = np.stack([labels[order], elem_for_weights[order]], 1)
    new_run = np.r_[True, (key[1:] != key[:-1]).any(1)]
    b.run_start = np.flatnonzero(new_run)
    b.run_len = np.diff(np.r_[b.run_start, V])
    b.run_corners = b.tidx[b.run_start]
    b.run_island = b._slot_island[b.run_start]
    finish(b, rel, tris, labels, V)
    return b
