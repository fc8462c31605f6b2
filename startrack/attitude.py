"""Attitude from vector pairs: Wahba's problem (paper 000 Eqs. 15-26).

Find the rotation ``A`` minimising ``L(A) = 1/2 sum a_i |b_i - A r_i|^2``
(Eq. 15) for body (camera) vectors ``b_i`` and reference (ICRS) vectors
``r_i``.  ``B = sum a_i b_i r_i^T`` (Eq. 19) is the attitude profile matrix and
``L(A) = lambda_0 - tr(A B^T)`` (Eq. 18).
"""
from __future__ import annotations

import numpy as np

__all__ = ["profile_matrix", "svd_solve", "wahba_loss"]


def profile_matrix(body, reference, weights=None):
    """``B = sum a_i b_i r_i^T`` (paper 000 Eq. 19)."""
    b = np.asarray(body, dtype=np.float64)
    r = np.asarray(reference, dtype=np.float64)
    a = np.ones(len(b)) if weights is None else np.asarray(weights, dtype=np.float64)
    return np.einsum("i,ij,ik->jk", a, b, r)


def svd_solve(body, reference, weights=None):
    """Markley's SVD solution (1988) with the determinant sign fixed: never a reflection.

    ``B = U S V^T``, ``A = U diag(1, 1, det U det V) V^T``.
    """
    bmat = profile_matrix(body, reference, weights)
    u, _, vt = np.linalg.svd(bmat)
    d = np.linalg.det(u) * np.linalg.det(vt)
    return u @ np.diag([1.0, 1.0, d]) @ vt


def wahba_loss(dcm, body, reference, weights=None):
    """``L(A) = 1/2 sum a_i |b_i - A r_i|^2`` (paper 000 Eq. 15)."""
    b = np.asarray(body, dtype=np.float64)
    r = np.asarray(reference, dtype=np.float64)
    a = np.ones(len(b)) if weights is None else np.asarray(weights, dtype=np.float64)
    diff = b - r @ np.asarray(dcm).T
    return 0.5 * float(np.sum(a * np.sum(diff * diff, axis=1)))
