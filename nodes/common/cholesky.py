"""A sparse symmetric positive definite matrix of one fixed pattern, factorised again and again with new values.

Two routes, the same solutions to rounding:
  cholmod   CHOLMOD's supernodal Cholesky (SuiteSparse, through cvxopt: GPL-3, so an optional dependency, the
            ``cholmod`` extra; ./setup.sh installs it), its fill-reducing order and symbolic analysis found once
            per pattern: track's normal equations (1935 unknowns at 20k vertices) 2.2-2.8 ms a factorisation, a
            solve 0.15 ms (bench/track.py ``speed``)
  superlu   scipy's SuperLU in a minimum-degree order found once (MMD on A + A^T), diagonal pivots: 7.9-9.8 ms,
            a solve 0.28-0.36 ms; used when cvxopt is not installed (``ROUTE``)
A matrix CHOLMOD finds not positive definite is solved by SuperLU with partial pivoting instead, with a warning
(an exactly singular one then raises SuperLU's error; the fit's 1e-8 diagonal keeps its systems regular).
Which route ran is part of every cache key (nodegraph/environment.py lists cvxopt's version, None without it).

    chol = SparseCholesky(pattern)            # lower triangle, CSC, sorted indices: only the positions count
    chol.factor(values)                       # values in pattern.data's order
    x = chol.solve(b)

One object holds one factorisation at a time: fits that share it run one after another.
"""
from __future__ import annotations

import logging
from importlib.util import find_spec

import numpy as np

LOG = logging.getLogger("volcap.cholesky")
ROUTE = "cholmod" if find_spec("cvxopt") is not None else "superlu"


class SparseCholesky:
    """Factors of symmetric positive definite matrices sharing ``pattern``'s lower triangle (scipy CSC with
    sorted indices), by ``route`` (module docstring)."""

    def __init__(self, pattern, route: str | None = None):
        n = pattern.shape[0]
        cols = np.repeat(np.arange(n), np.diff(pattern.indptr))
        if np.any(pattern.indices < cols):
            raise ValueError("SparseCholesky: the pattern must be the lower triangle (row >= column)")
        if np.any((np.diff(pattern.indices) <= 0) & (np.diff(cols) == 0)):
            raise ValueError("SparseCholesky: the pattern must have sorted indices and no duplicates")
        self.pattern = pattern.copy()
        self.route = route or ROUTE
        self.lu = None
        if self.route == "cholmod":
            from cvxopt import cholmod, spmatrix

            # the cvxopt matrix stores its values in CSC order, so they line up with pattern.data (checked)
            slots = np.arange(1.0, len(cols) + 1)
            self.A = spmatrix(slots, pattern.indices.tolist(), cols.tolist(), (n, n))
            if not np.array_equal(np.asarray(self.A.V).ravel(), slots):
                raise ValueError("SparseCholesky: cvxopt stored the pattern in another order")
            self.symbolic = cholmod.symbolic(self.A)
        else:
            from scipy.sparse.linalg import splu

            # the whole symmetric pattern, each of its values a slot of ours, in a minimum-degree order found once
            # (structural: a diagonally dominant matrix of the pattern gives it)
            full = self.full(np.arange(1.0, len(cols) + 1)).tocoo()
            dominant = full.copy()
            dominant.data = np.where(full.row == full.col, 10.0 * len(cols), -1.0)
            position = splu(dominant.tocsc(), permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True}).perm_c
            self.order = np.argsort(position)                                     # position -> unknown
            self.position = position
            permuted = full.copy()
            permuted.row, permuted.col = position[full.row], position[full.col]
            permuted = permuted.tocsc()
            permuted.sort_indices()
            self.permuted = permuted
            self.slot = permuted.data.astype(np.int64) - 1                        # permuted CSC slot -> ours

    def factor(self, values: np.ndarray) -> None:
        from scipy.sparse.linalg import splu

        values = np.ascontiguousarray(values, np.float64)
        self.lu = None
        if self.route == "cholmod":
            from cvxopt import cholmod, matrix

            self.A.V = matrix(values)
            try:
                cholmod.numeric(self.A, self.symbolic)
                return
            except ArithmeticError:
                LOG.warning("the system is not positive definite (CHOLMOD): solved by SuperLU with pivoting instead")
                self.lu = ("pivoting", splu(self.full(values).tocsc()))
                return
        A = self.permuted.copy()
        A.data = values[self.slot]
        self.lu = ("ordered", splu(A, permc_spec="NATURAL", diag_pivot_thresh=0.0, options={"SymmetricMode": True}))

    def solve(self, b: np.ndarray) -> np.ndarray:
        b = np.ascontiguousarray(b, np.float64)
        if self.lu is None:
            from cvxopt import cholmod, matrix

            x = matrix(b)
            cholmod.solve(self.symbolic, x)
            return np.asarray(x).ravel()
        kind, lu = self.lu
        return lu.solve(b) if kind == "pivoting" else lu.solve(b[self.order])[self.position]

    def full(self, values: np.ndarray):
        """The whole symmetric matrix (scipy CSR) with ``values`` in the pattern's lower triangle."""
        from scipy.sparse import diags

        low = self.pattern.copy()
        low.data = np.asarray(values, np.float64)
        return (low + low.T - diags(low.diagonal())).tocsr()

    def reference(self, values: np.ndarray, b: np.ndarray) -> np.ndarray:
        """The same solve by scipy's SuperLU (partial pivoting, its own column order)."""
        from scipy.sparse.linalg import splu

        return splu(self.full(values).tocsc()).solve(np.asarray(b, np.float64))
