"""Low-level pieces of polyhedral cells shared by cages, their refinement and their embedding:
how a face splits into triangles, tetrahedron volumes and corner-weight derivatives, and the
unique rows of an integer table. Nothing here imports another module of the package."""
import numpy as np


def face_triangles(f):
    """Triangles (a, b, c) of an outward face loop f; -1 stands for the face's centroid."""
    n = len(f)
    if n == 3:
        return [tuple(f)]
    if n == 4:
        k = int(np.argmin(f))   # the diagonal through the lowest index, the same from both sides
        a, b, c, d = (f[(k + j) % 4] for j in range(4))
        return [(a, b, c), (a, c, d)]
    return [(-1, f[j], f[(j + 1) % n]) for j in range(n)]


def tet_volumes(tets):
    """(k,) signed volumes of tetrahedra (k, 4, 3)."""
    a = tets[:, 1] - tets[:, 0]
    b = tets[:, 2] - tets[:, 0]
    c = tets[:, 3] - tets[:, 0]
    return np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0


def unique_rows(a):
    """(unique rows (u, k), inverse (m,)) of an int array (m, k), rows in lexicographic order.
    Columns are folded into one int64 key a pair at a time, ranked in between, so keys never
    overflow."""
    a = np.asarray(a, np.int64)
    key = a[:, 0] - a[:, 0].min()
    for j in range(1, a.shape[1]):
        col = a[:, j] - a[:, j].min()
        key = key * (int(col.max()) + 1) + col
        if j < a.shape[1] - 1:
            key = np.unique(key, return_inverse=True)[1].ravel()
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    return a[first], inverse.ravel()


#: d(weights)/d(barycentric coordinates) (8, 3) of a tetrahedron's corners, laid out as the eight
#: corner weights of a hexahedron (the last four unused).
TET_DW = np.zeros((8, 3))
TET_DW[0] = -1.0
TET_DW[1:4] = np.eye(3)
