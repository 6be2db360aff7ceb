"""Closed triangle meshes for examples, tests and benchmarks (NumPy only)."""
import numpy as np


def icosphere(subdivisions=3, radius=1.0, center=(0.0, 0.0, 0.0)):
    """Geodesic sphere: (verts (V, 3), tris (F, 3)) with V = 10 * 4**s + 2, outward normals."""
    t = (1 + 5 ** 0.5) / 2
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                  [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
                  [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
                  [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    v /= np.linalg.norm(v, axis=1)[:, None]
    for _ in range(int(subdivisions)):
        # One midpoint per undirected edge, shared by the two faces that use it.
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        unique, inverse = np.unique(edges, axis=0, return_inverse=True)
        mid = v[unique[:, 0]] + v[unique[:, 1]]
        mid /= np.linalg.norm(mid, axis=1)[:, None]
        ab, bc, ca = inverse.reshape(3, -1) + len(v)
        v = np.vstack([v, mid])
        a, b, c = f.T
        f = np.concatenate([np.stack(x, 1) for x in ((a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca))])
    return v * radius + np.asarray(center, float), f


def box(resolution=1, size=1.0, center=(0.0, 0.0, 0.0)):
    """Cube of edge `size` whose faces are split into resolution x resolution quads, two triangles
    each: (verts (V, 3), tris (F, 3)) with outward normals and shared vertices along the edges."""
    n = int(resolution)
    if n < 1:
        raise ValueError(f"box resolution must be >= 1, got {resolution!r}")
    g = np.linspace(-0.5, 0.5, n + 1)
    # All lattice points of the (n+1)^3 grid that lie on the surface, indexed through a full grid.
    ii, jj, kk = np.meshgrid(np.arange(n + 1), np.arange(n + 1), np.arange(n + 1), indexing="ij")
    on_surface = (np.minimum.reduce([ii, jj, kk]) == 0) | (np.maximum.reduce([ii, jj, kk]) == n)
    index = -np.ones((n + 1,) * 3, np.int64)
    index[on_surface] = np.arange(on_surface.sum())
    verts = np.stack([g[ii[on_surface]], g[jj[on_surface]], g[kk[on_surface]]], 1)
    tris = []
    a, b = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a, b = a.ravel(), b.ravel()
    for axis in range(3):
        for side, flip in ((0, True), (n, False)):
            def at(p, q):
                c = [None, None, None]
                c[axis] = np.full_like(p, side)
                c[(axis + 1) % 3], c[(axis + 2) % 3] = p, q
                return index[c[0], c[1], c[2]]
            q00, q10, q11, q01 = at(a, b), at(a + 1, b), at(a + 1, b + 1), at(a, b + 1)
            quad = np.stack([q00, q10, q11, q01], 1)
            if flip:
                quad = quad[:, ::-1]
            tris.append(quad[:, [0, 1, 2]])
            tris.append(quad[:, [0, 2, 3]])
    return verts * size + np.asarray(center, float), np.concatenate(tris)
