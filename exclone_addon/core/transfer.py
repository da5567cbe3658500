"""Deformation transfer (Sumner & Popovic 2004; docs/method.md §8) with one factorisation for
all expressions.

For target displacements d: min sum over target triangles w_t ||S_t - T_t(x0 + d)||_F^2, where
S_t is the source gradient the correspondence gives triangle t (weight w_t), and the identity
(weight 1) on target triangles the correspondence does not cover (they follow without deforming). The normal matrix
depends on the target neutral and the pairs only, so it is factorised once and every expression
is a back-substitution; all expressions go through as one multi-column right-hand side.

Solving for displacements makes a zero expression give exactly zero. Gradients fix a shape only
up to a translation per connected part, so each part's translation is set afterwards: covered
parts take the source's mean displacement at their vertices' corresponding points, parts with no
correspondence stay where they are.

The normal matrix is symmetric positive definite, so it is factorised with a sparse Cholesky
(cholespy, bundled with the extension) where that is installed: at 50k target vertices it
factorises and solves in a fraction of SuperLU's time, and SuperLU's fill-in grows out of hand
beyond. SuperLU remains the fallback (a Blender without cholespy, or a matrix rounding makes
indefinite); on the demo head both give the same displacements to 5e-14 of their size.
"""
import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

try:
    import cholespy
except ImportError:     # an install without the bundled wheel: SuperLU serves alone
    cholespy = None

from . import deformation
from .errors import ExCloneError
from .mesh import vertex_parts


CHOLESKY = "cholesky"
LU = "lu"


def factorised(matrix):
    """(name, solve) for the symmetric positive definite CSC `matrix`: solve(B) returns
    matrix^-1 B for a (N,) or (N, k) B. Sparse Cholesky where cholespy is installed and finds
    the matrix positive definite, else SuperLU."""
    if not matrix.count_nonzero():      # all zero: cholespy fails on it, then aborts the process
        raise _no_unique_solution()
    if cholespy is not None:
        try:
            return CHOLESKY, _cholesky(matrix)
        except ValueError:      # cholespy: "Matrix is not positive definite!"
            pass
    return LU, _lu(matrix)


def _cholesky(matrix):
    lower = sp.tril(matrix, format="csc")       # CHOLMOD reads the lower triangle only
    factor = cholespy.CholeskySolverD(matrix.shape[0], lower.indptr.astype(np.int32),
                                      lower.indices.astype(np.int32),
                                      np.ascontiguousarray(lower.data, dtype=np.float64),
                                      cholespy.MatrixType.CSC)

    def solve(rhs):
        # every column in one call (rows = unknowns, C order), as cholespy expects
        rhs = np.ascontiguousarray(rhs, dtype=np.float64)
        solution = np.empty_like(rhs)
        factor.solve(rhs, solution)
        return solution
    return solve


def _lu(matrix):
    try:
        factor = splu(matrix, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                      options={"SymmetricMode": True})
    except RuntimeError as exc:       # SuperLU: "Factor is exactly singular"
        raise _no_unique_solution() from exc
    return lambda rhs: factor.solve(np.ascontiguousarray(rhs))


def _no_unique_solution():
    return ExCloneError("the transfer's equations have no unique solution (the target mesh's "
                        "triangles are too thin); clean up the mesh")


class Transfer:
    def __init__(self, target_vertices, target_triangles, weights,
                 formulation=deformation.REDUCED, fixed=()):
        """weights: (T,) per target triangle; 0 marks a triangle with no source gradient.
        fixed: (k,) target vertex ids held at exactly zero displacement (e.g. the cut border of
        a head cut out of a body): their unknowns are eliminated from the normal equations, and
        a connected part holding any of them is not re-translated afterwards."""
        self.n = len(target_vertices)
        self.grad, _ = deformation.gradient_operator(target_vertices, target_triangles, formulation)
        self.rest = deformation.unknowns_of(target_vertices, target_triangles, formulation)
        self.uncovered = np.asarray(weights) <= 0
        self.uncovered_rows = np.repeat(self.uncovered, 3)          # their rows in G's layout
        self.identity_blocks = np.tile(np.eye(3), (int(self.uncovered.sum()), 1))
        self.row_weight = np.where(self.uncovered, 1.0, weights)
        self.fixed = _checked_fixed(fixed, self.n)
        self.free = np.ones(self.grad.shape[1], dtype=bool)
        self.free[self.fixed] = False
        w_rows = sp.diags(np.repeat(self.row_weight, 3))
        normal = (self.grad.T @ w_rows @ self.grad).tocsc()
        normal = normal[self.free][:, self.free]       # Dirichlet: fixed unknowns are 0
        # a whisper of regularisation keeps the per-part translations definite; they are set
        # explicitly afterwards (see module docstring)
        eps = 1e-10 * normal.diagonal().mean()
        self.factorisation, self.solve = factorised(
            (normal + eps * sp.identity(normal.shape[0], format="csc")).tocsc())
        self.rest_gradients = self.grad @ self.rest                             # (3T, 3)
        self.parts = vertex_parts(self.n, target_triangles)

    def __call__(self, target_gradients, anchor_displacements=None, anchor_vertices=None):
        """target_gradients: (E, T, 3, 3) the source gradient each target triangle should take
        (ignored where uncovered).

        anchor_displacements: (E, k, 3) the source's displacement at the corresponding points of
        target vertices anchor_vertices (k,), to set each covered part's translation.
        Returns target displacements (E, n, 3).
        """
        e = len(target_gradients)
        # in place on one stacked copy: at 100k triangles and 57 expressions each (E, 3T, 3)
        # array is 400 MB, and allocating more of them cost more than the solve
        given = np.asarray(target_gradients, dtype=np.float64)
        residual = deformation.stack_gradients(given)
        if np.may_share_memory(residual, given):     # a view (e.g. one triangle): never write
            residual = residual.copy()               # into the caller's array
        residual[:, self.uncovered_rows] = self.identity_blocks                # (E, 3T, 3)
        residual -= self.rest_gradients
        residual *= np.repeat(self.row_weight, 3)[:, None]
        rhs = self.grad.T @ residual.transpose(1, 0, 2).reshape(-1, e * 3)     # (N, 3E)
        solution = np.zeros_like(rhs)
        solution[self.free] = self.solve(rhs[self.free])
        d = solution.reshape(-1, e, 3).transpose(1, 0, 2)[:, : self.n]         # (E, n, 3)
        return self._anchor(d, anchor_displacements, anchor_vertices)

    def _anchor(self, d, anchor_displacements, anchor_vertices):
        parts = self.parts
        count = np.bincount(parts)
        shift = -np.stack([np.stack([np.bincount(parts, d[k, :, c], len(count)) for c in range(3)], 1)
                           for k in range(len(d))]) / count[None, :, None]       # (E, P, 3)
        if anchor_vertices is not None and len(anchor_vertices):
            owner = parts[anchor_vertices]
            n_anchor = np.bincount(owner, minlength=len(count))
            gap = anchor_displacements - d[:, anchor_vertices]                  # (E, k, 3)
            sums = np.stack([np.stack([np.bincount(owner, gap[k, :, c], len(count))
                                       for c in range(3)], 1) for k in range(len(d))])
            anchored = n_anchor > 0
            shift[:, anchored] = sums[:, anchored] / n_anchor[anchored, None]
        shift[:, np.unique(parts[self.fixed])] = 0.0     # held by their fixed vertices
        return d + shift[:, parts]


def _checked_fixed(fixed, n_vertices):
    """The fixed vertex ids as a sorted unique int array, or ExCloneError if one is no vertex."""
    fixed = np.unique(np.asarray(fixed, dtype=np.int64).ravel())
    if len(fixed) and (fixed[0] < 0 or fixed[-1] >= n_vertices):
        raise ExCloneError(f"fixed vertex ids must lie in [0, {n_vertices}); got "
                           f"{fixed[0]}..{fixed[-1]}")
    return fixed
