"""A minimal row-compressed sparse matrix (SciPy is not available inside Blender)."""
import numpy as np


class Sparse:
    """(n_rows, n_cols) matrix stored as row index, column index and value arrays, sorted by row.

    Only what the cage refinement needs: products with vectors or (n, k) blocks from either side,
    and composition.
    """

    def __init__(self, rows, cols, vals, shape):
        rows = np.asarray(rows, np.int64)
        cols = np.asarray(cols, np.int64)
        vals = np.asarray(vals, np.float64)
        # Merge duplicate entries so that every (row, col) appears once.
        key = rows * shape[1] + cols
        uniq, inv = np.unique(key, return_inverse=True)
        self.vals = np.bincount(inv.ravel(), vals, len(uniq))
        self.rows, self.cols = np.divmod(uniq, shape[1])
        self.shape = (int(shape[0]), int(shape[1]))

    @property
    def nnz(self):
        return len(self.vals)

    def matvec(self, x):
        """A @ x for x (n_cols,) or (n_cols, k): (n_rows,) or (n_rows, k) float64."""
        x = np.asarray(x, np.float64)
        prod = self.vals * x[self.cols] if x.ndim == 1 else self.vals[:, None] * x[self.cols]
        if x.ndim == 1:
            return np.bincount(self.rows, prod, self.shape[0])
        return np.stack([np.bincount(self.rows, prod[:, j], self.shape[0]) for j in range(x.shape[1])], 1)

    def rmatvec(self, y):
        """A.T @ y for y (n_rows,) or (n_rows, k): (n_cols,) or (n_cols, k) float64."""
        y = np.asarray(y, np.float64)
        if y.ndim == 1:
            return np.bincount(self.cols, self.vals * y[self.rows], self.shape[1])
        prod = self.vals[:, None] * y[self.rows]
        return np.stack([np.bincount(self.cols, prod[:, j], self.shape[1]) for j in range(y.shape[1])], 1)

    def compose(self, other):
        """self @ other (another `Sparse`) as a `Sparse`."""
        if self.shape[1] != other.shape[0]:
            raise ValueError(f"shapes {self.shape} and {other.shape} do not compose")
        start = np.searchsorted(other.rows, np.arange(other.shape[0] + 1))
        count = np.diff(start)[self.cols]
        rep = np.repeat(np.arange(self.nnz), count)
        # Position of every expanded entry inside its row of `other`.
        offset = np.arange(len(rep)) - np.repeat(np.cumsum(count) - count, count)
        k = start[self.cols][rep] + offset
        return Sparse(self.rows[rep], other.cols[k], self.vals[rep] * other.vals[k],
                      (self.shape[0], other.shape[1]))
