"""The elementwise 3x3/4x4 linear algebra against LAPACK (NumPy's linalg) on random stacks."""
import numpy as np
import pytest

from vpffd_addon import linalg3

pytestmark = pytest.mark.core


def _stack(seed, n=200):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, 3, 3))
    A[0] = np.diag([1e-3, 2.0, 5e2])           # badly scaled but invertible
    return A


def test_det_inverse_and_solve_match_lapack():
    A = _stack(1)
    np.testing.assert_allclose(linalg3.det3(A), np.linalg.det(A), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(linalg3.inv3(A), np.linalg.inv(A), rtol=1e-8, atol=1e-8)
    b = np.random.default_rng(2).normal(size=(len(A), 3))
    np.testing.assert_allclose(linalg3.solve3(A, b), np.linalg.solve(A, b[:, :, None])[:, :, 0],
                               rtol=1e-8, atol=1e-8)
    B = np.random.default_rng(3).normal(size=(len(A), 3, 3))
    np.testing.assert_allclose(linalg3.solve3(A, B), np.linalg.solve(A, B), rtol=1e-8, atol=1e-8)


def test_singular_matrix_gives_non_finite_inverse_not_an_exception():
    A = np.array([[1.0, 2, 3], [2, 4, 6], [0, 1, 1]])
    assert linalg3.det3(A) == 0.0
    assert not np.isfinite(linalg3.inv3(A)).all()


def test_affine_map_and_inverse_match_homogeneous_products():
    rng = np.random.default_rng(4)
    M = np.eye(4)
    M[:3, :] = rng.normal(size=(3, 4))
    p = rng.normal(size=(50, 3))
    homogeneous = np.c_[p, np.ones(len(p))] @ M.T
    np.testing.assert_allclose(linalg3.affine(p, M), homogeneous[:, :3], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(linalg3.affine_inverse(M), np.linalg.inv(M), rtol=1e-9, atol=1e-9)
    N = np.eye(4)
    N[:3, :] = rng.normal(size=(3, 4))
    np.testing.assert_allclose(linalg3.matmul4(M, N, M), M @ N @ M, rtol=1e-12, atol=1e-12)
