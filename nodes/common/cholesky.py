"""A sparse symmetric positive definite matrix of one fixed pattern, factorised again and again with new values:
CHOLMOD's supernodal Cholesky (SuiteSparse, through cvxopt), its fill-reducing order and symbolic analysis found
once per pattern; ``reference`` solves the same system with scipy's SuperLU (what track used before; a test
compares the two). Track's normal equations (a few thousand unknowns, refactorised every ICP iteration): 2.2-2.8
ms a factorisation against SuperLU's 8.4-9.8 ms in a precomputed order, a solve 0.15 against 0.36 ms (bench/track.py
``speed``).

    chol = SparseCholesky(pattern)            # lower triangle, CSC, sorted indices: only the positions count
    chol.factor(values)                       # values in pattern.data's order
    x = chol.solve(b)
"""
from __future__ import annotations

import logging

import numpy as np

LOG = logging.getLogger("volcap.cholesky")


class SparseCholesky:
    """Cholesky factors of symmetric positive definite matrices sharing ``pattern``'s lower triangle (scipy CSC
    with sorted indices). A matrix CHOLMOD finds not positive definite (a singular system) is solved by SuperLU
    with partial pivoting instead, with a warning: the answer a general sparse solver gives, never a crash."""

    def __init__(self, pattern):
        from cvxopt import cholmod, spmatrix

        self.pattern = pattern.copy()
        n = pattern.shape[0]
        cols = np.repeat(np.arange(n), np.diff(pattern.indptr))
        if np.any(pattern.indices < cols):
            raise ValueError("SparseCholesky: the pattern must be the lower triangle (row >= column)")
        # values 1..nnz: the cvxopt matrix stores its values in CSC order, so they line up with pattern.data (checked)
        slots = np.arange(1.0, len(pattern.indices) + 1)
        self.A = spmatrix(slots, pattern.indices.tolist(), cols.tolist(), (n, n))
        if not np.array_equal(np.asarray(self.A.V).ravel(), slots):
            raise ValueError("SparseCholesky: the pattern must have sorted indices and no duplicates")
        self.symbolic = cholmod.symbolic(self.A)
        self.lu = None

    def factor(self, values: np.ndarray) -> None:
        from cvxopt import cholmod, matrix

        values = np.ascontiguousarray(values, np.float64)
        self.A.V = matrix(values)
        self.lu = None
        try:
            cholmod.numeric(self.A, self.symbolic)
        except ArithmeticError:
            from scipy.sparse.linalg import splu

            LOG.warning("the system is not positive definite (CHOLMOD): solved by SuperLU with pivoting instead")
            self.lu = splu(self.full(values).tocsc())

    def solve(self, b: np.ndarray) -> np.ndarray:
        from cvxopt import cholmod, matrix

        if self.lu is not None:
            return self.lu.solve(np.asarray(b, np.float64))
        x = matrix(np.ascontiguousarray(b, np.float64))
        cholmod.solve(self.symbolic, x)
        return np.asarray(x).ravel()

    def full(self, values: np.ndarray):
        """The whole symmetric matrix (scipy CSR) with ``values`` in the pattern's lower triangle."""
        low = self.pattern.copy()
        low.data = np.asarray(values, np.float64)
        return (low + low.T - _diagonal(low)).tocsr()

    def reference(self, values: np.ndarray, b: np.ndarray) -> np.ndarray:
        """The same solve by scipy's SuperLU (partial pivoting, its own column order)."""
        from scipy.sparse.linalg import splu

        return splu(self.full(values).tocsc()).solve(np.asarray(b, np.float64))


def _diagonal(m):
    from scipy.sparse import diags

    return diags(m.diagonal())
