"""Deformation transfer (Sumner & Popovic 2004; docs/method.md §8) with one factorisation for
all expressions.

For target displacements d: min sum over target triangles w_t ||S_t - T_t(x0 + d)||_F^2, where
S_t is the source gradient the correspondence gives triangle t (weight w_t), and the identity
(weight 1) on target triangles the correspondence does not cover (they follow without
deforming). The normal matrix depends on the target neutral and the pairs only, so it is
factorised once and every expression is a back-substitution.

The expressions go through in blocks of EXPRESSIONS_PER_BLOCK, each block one multi-column
right-hand side, so no array grows with the number of expressions times the number of
triangles (57 expressions' (E, T, 3, 3) gradients in float64 are 0.8 GB at 100k triangles, and
the solve used to hold several such arrays). CorrespondedTransfer goes further: it never forms
the source gradients at all, only the sparse operators that take the source's motion to the
right-hand side (the peak memory of a clone grows by about 5 KiB per target vertex with 57
expressions, most of it the result itself).

Solving for displacements makes a zero expression give exactly zero. Gradients fix a shape only
up to a translation per connected part, so each part's translation is set afterwards: covered
parts take the source's mean displacement at their vertices' corresponding points, parts with no
correspondence stay where they are. Fixed vertices (Dirichlet: exactly zero displacement, their
unknowns eliminated) hold their part in place instead.

The normal matrix is symmetric positive definite, so it is factorised with a sparse Cholesky
(cholespy, bundled with the extension) where that is installed: at 50k target vertices it
factorises and solves in a fraction of SuperLU's time, and SuperLU's fill-in grows out of hand
beyond. SuperLU remains the fallback (a Blender without cholespy, or a matrix rounding makes
indefinite); on the demo head both give the same displacements to 5e-14 of their size.
"""
from functools import cached_property

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu
from scipy.spatial.transform import Rotation

try:
    import cholespy
except ImportError:     # an install without the bundled wheel: SuperLU serves alone
    cholespy = None

from . import deformation
from .expression_measures import excess_stretches, source_turns_beside, turned_over
from .errors import ExCloneError
from .mesh import triangle_normals, unique_edges, vertex_parts
from .proximity import components_dot


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


# Expressions solved together: every (E, ...) array of the transfer is made for this many at a
# time, so its memory does not grow with the number of expressions; more per block gains little
# (the factor's back-substitution is as fast per column from about 8 columns on).
EXPRESSIONS_PER_BLOCK = 8
# Mapped triangles whose images' 4th vertices are made together (memory-bound elementwise work)
TRIANGLES_PER_CHUNK = 8192
# Target edges whose stretch (STRETCH_BOUND) is measured together, for the same reason
EDGES_PER_CHUNK = 8192
# A mapped triangle's image may stretch (its largest stretch within its plane, per expression)
# at most this many times as far as the most stretched source triangle under its corners (or
# 1): beyond, its corners' images lie on two sides of an opening that parts (the lips at a mouth
# corner, where the library closes its corners with a strip of thin triangles), and it takes the
# mean gradient of the source triangles under its corners instead. Within one source triangle an
# image stretches exactly as that triangle does; spanning the source triangles between its
# corners it read up to 2.4 on the remeshed known-answer face (its exact registration), across
# the parting lips 105-110 (the old woman's triangulated body, a torn mouth corner).
STRADDLE = 3.0
# The bar: no target edge stretched more than this beyond its image's stretch on the
# source (expression_measures.excess_stretches). Where a solved expression passes it, the goals
# of the triangles around the passing edges take their singular values capped at it (their
# rotations kept), the same triangles for every expression transferred together, and what that
# changes is solved alone (the solve is linear; the factorisation is kept). The region grows by
# a ring of triangles a round while a passing expression's worst edge gives way by GIVING_WAY,
# for at most BOUND_ROUNDS rounds. The library's mouth corners open in a strip of thin triangles
# stretched 7-37x; target triangles whose images fall on it take that stretch beside edges
# whose own images lie off it (docs/method.md §8, "Stretch bounded").
STRETCH_BOUND = 2.5
BOUND_ROUNDS = 8           # the child's mouth-open onto the ICT neutral needed 7
# Just past STRETCH_BOUND the capped goals move only part of the way to their caps, the share
# (worst excess stretch of the call - STRETCH_BOUND) / BOUND_FADE, all of it from
# STRETCH_BOUND + BOUND_FADE on: a call whose worst edge passes the bar by a hair moves by a hair
# (with the whole cap at once, 2.1% of the clone). The characters' and the 50k case's worst
# edges, 2.8-3.6 before the bound, take the whole cap as before.
BOUND_FADE = 0.25
GIVING_WAY = 0.99          # at 50k vertices one edge crept 2.5674 -> 2.5666 over four rounds
# A target triangle an expression turns over (expression_measures.turned_over) where neither its
# image on the source nor the images of the triangles beside it turn over is the transfer's own
# tangle, not the source's motion (the library's jawOpen turns the inner lower lip at its
# corners by 80-110 degrees; the target triangles whose goals follow it land a few degrees either
# side of 90). Its goal, its solved gradient turned back to its image's turn, weighs
# TANGLED_WEIGHT times its neighbours' (their solved gradients) in a solve of its corners and a
# ring of triangles around them, the rest held; at most UNTANGLE_ROUNDS rounds (docs/method.md
# §8, "Untangled"). With the weight 1 a tangle on the male body and one on the old woman's stayed.
TANGLED_WEIGHT = 4.0
UNTANGLE_ROUNDS = 4


class Transfer:
    def __init__(self, target_vertices, target_triangles, weights,
                 formulation=deformation.REDUCED, fixed=(), gradient=None):
        """weights: (T,) per target triangle; 0 marks a triangle with no source gradient.
        fixed: (k,) target vertex ids held at exactly zero displacement (e.g. the cut border of
        a head cut out of a body): their unknowns are eliminated from the normal equations, and
        a connected part holding any of them is not re-translated afterwards. gradient: the
        target's deformation.gradient_operator in this formulation, if made already (a fit
        makes it while it waits for the landmarks)."""
        self.n = len(target_vertices)
        self.rest_vertices = np.asarray(target_vertices, dtype=np.float64)
        self.triangles = np.asarray(target_triangles)
        self.grad = gradient if gradient is not None else \
            deformation.gradient_operator(target_vertices, target_triangles, formulation)[0]
        uncovered = np.asarray(weights) <= 0
        self.row_weight = np.where(uncovered, 1.0, weights)
        # the rows a given gradient enters with its weight (uncovered ones take the identity)
        self.given_rows_weight = np.repeat(np.where(uncovered, 0.0, weights), 3)
        self.uncovered_rows = np.repeat(uncovered, 3)
        self.fixed = _checked_fixed(fixed, self.n)
        self.free = np.ones(self.grad.shape[1], dtype=bool)
        self.free[self.fixed] = False
        self.factorisation, self.solve = factorised(self.normal_matrix)
        self.constant = self._constant_rhs(target_vertices, target_triangles, formulation)
        self.parts = vertex_parts(self.n, target_triangles)
        self._part_sums, self._held_parts = self._part_sums_and_held()
        self._kept_anchoring = None

    @cached_property
    def normal_matrix(self):
        """G^T W G on the free unknowns (fixed ones are 0: Dirichlet), with a whisper of
        regularisation that keeps the per-part translations definite (they are set explicitly
        afterwards, see the module docstring). Kept: the rims' correction adds to it."""
        normal = (self.grad.T @ sp.diags(np.repeat(self.row_weight, 3)) @ self.grad).tocsc()
        return whispered(normal[self.free][:, self.free])

    def _constant_rhs(self, vertices, triangles, formulation):
        """(N, 3) the share of the right-hand side no expression changes: the identity on
        uncovered triangles, minus the rest shape's own gradients (the unknowns are
        displacements)."""
        rest = deformation.unknowns_of(vertices, triangles, formulation)
        residual = -(self.grad @ rest)                                          # (3T, 3)
        residual[self.uncovered_rows] += deformation.stacked_identity(
            int(self.uncovered_rows.sum()) // 3)
        return self.grad.T @ (np.repeat(self.row_weight, 3)[:, None] * residual)

    def _part_sums_and_held(self):
        """(P x n) sparse sum over each connected part, and the parts holding a fixed vertex."""
        n_parts = int(self.parts.max(initial=-1)) + 1
        sums = sp.csr_matrix((np.ones(self.n), (self.parts, np.arange(self.n))),
                             shape=(n_parts, self.n))
        return sums, np.unique(self.parts[self.fixed])

    def pulled(self, operator, triangle_ids):
        """G^T W over the rows of triangles `triangle_ids` (m,), times `operator` (3m x K) that
        gives those triangles' stacked gradients (G's layout): the sparse (N x K) that takes
        whatever the operator is applied to into the right-hand side."""
        rows = (3 * np.asarray(triangle_ids)[:, None] + np.arange(3)).ravel()
        weighted = sp.diags(self.given_rows_weight[rows]) @ operator
        return (self.grad[rows].T @ weighted).tocsr()

    def right_hand_side(self, stacked):
        """(N, 3B) right-hand sides of B expressions' stacked target gradients (B, 3T, 3), in
        the solve's layout (as_columns)."""
        weighted = as_columns(stacked) * self.given_rows_weight[:, None]
        weighted[self.uncovered_rows] = 0.0          # ignored there, whatever they hold
        return self.grad.T @ weighted + np.repeat(self.constant, len(stacked), axis=1)

    def solved(self, rhs, anchor_moves=None, anchor_vertices=None, solve=None):
        """(n, 3B) target displacements of right-hand sides rhs (N, 3B); anchor_moves (k, 3B):
        the source's displacement at the corresponding points of target vertices
        anchor_vertices (k,), to set each covered part's translation. solve: another system's
        solve over the free unknowns (default: this one's normal matrix)."""
        solve = solve or self.solve
        if self.free.all():
            solution = solve(rhs)
        else:
            solution = np.zeros_like(rhs)
            solution[self.free] = solve(rhs[self.free])
        return self._anchored(solution[: self.n], anchor_moves, anchor_vertices)

    def __call__(self, target_gradients, anchor_displacements=None, anchor_vertices=None):
        """target_gradients: (E, T, 3, 3) the source gradient each target triangle should take
        (ignored where uncovered).

        anchor_displacements: (E, k, 3) the source's displacement at the corresponding points of
        target vertices anchor_vertices (k,), to set each covered part's translation.
        Returns target displacements (E, n, 3).
        """
        out = np.empty((len(target_gradients), self.n, 3))
        for block in blocks(len(target_gradients)):
            stacked = deformation.stack_gradients(np.asarray(target_gradients[block],
                                                             dtype=np.float64))
            moves = None if anchor_displacements is None else \
                as_columns(np.asarray(anchor_displacements[block], dtype=np.float64))
            out[block] = as_rows(self.solved(self.right_hand_side(stacked), moves,
                                             anchor_vertices))
        return out

    def _anchored(self, d, anchor_moves, anchor_vertices):
        """d (n, 3B) with each connected part translated: by the mean gap to its anchors' moves
        where it has anchors, else back to no mean motion; parts holding a fixed vertex stay."""
        anchored, anchor_sums, n_anchor, free_sums, free_count = self._anchoring(anchor_vertices)
        shift = np.empty((len(anchored), d.shape[1]))
        shift[~anchored] = -(free_sums @ d) / free_count
        if anchored.any():
            # np.take and the gap made in place: no (k, 3B) temporaries beside it
            gap = np.take(d, anchor_vertices, axis=0)
            np.subtract(anchor_moves, gap, out=gap)
            shift[anchored] = (anchor_sums @ gap) / n_anchor
        shift[self._held_parts] = 0.0
        d += np.take(shift, self.parts, axis=0)
        return d

    def _anchoring(self, anchor_vertices):
        """_anchored's sums for anchors anchor_vertices (k,) or None: ((P,) the parts with
        anchors, (P' x k) sparse sum over each one's anchors, (P', 1) their counts, (P'' x n)
        sparse sum over each other part's vertices, (P'', 1) their counts). Kept for the next
        call with the same anchors (every solve of a clone passes the same)."""
        anchor_vertices = np.zeros(0, dtype=np.int64) if anchor_vertices is None else \
            np.asarray(anchor_vertices)
        kept = self._kept_anchoring
        if kept is None or not np.array_equal(kept[0], anchor_vertices):
            count = np.asarray(self._part_sums.sum(axis=1))
            owner = self.parts[anchor_vertices]
            n_anchor = np.bincount(owner, minlength=len(count))
            anchored = n_anchor > 0
            by_part = sp.csr_matrix((np.ones(len(owner)), (owner, np.arange(len(owner)))),
                                    shape=(len(count), len(owner)))
            kept = (anchor_vertices.copy(), anchored, by_part[anchored],
                    n_anchor[anchored, None], self._part_sums[~anchored], count[~anchored])
            self._kept_anchoring = kept
        return kept[1:]


class CorrespondedTransfer:
    """A source's expressions carried through a correspondence onto the target (docs/method.md
    §7, §8), made once per fit: a target triangle whose corners map onto the source (the vertex
    map) takes the gradient of its image there, a paired one the weighted mean of its pairs'
    source gradients, the rest the identity.

    Every share of the right-hand side that is linear in the source's motion is one sparse
    operator made here, so an expression costs a few sparse products, the 4th vertices of its
    mapped triangles' images and a back-substitution, in blocks of EXPRESSIONS_PER_BLOCK: no
    (E, T, 3, 3) array of gradients is ever made."""

    def __init__(self, system, source_rest, source_triangles, vertex_map, mapped, pairs, weights):
        """system: the target's Transfer; source_rest (n_s, 3) and source_triangles (S, 3) the
        source region in the target's frame; vertex_map: correspondence.VertexMap onto those
        triangles; mapped (T,) the target triangles that take their image's gradient; pairs
        (T x S) sparse triangle pairs and weights (T,) as the fit made them."""
        self.system = system
        self.source_rest = source_rest
        self.anchors = np.flatnonzero(vertex_map.valid)
        self.sampling = _barycentric_sampling(vertex_map, source_triangles, self.anchors,
                                              system.n, len(source_rest))
        rest_at = self.sampling @ source_rest          # the source under each mapped vertex
        self.mapped_ids = np.flatnonzero(mapped)
        self._image_operators(rest_at, self.mapped_ids)
        self.constant = system.constant + self.from_moves @ rest_at
        self._straddle_checks(rest_at, source_triangles, vertex_map)
        self._pair_operators(source_triangles, pairs, weights, np.flatnonzero(~mapped & (weights > 0)))
        self._bound_checks(source_triangles, vertex_map, weights)

    @property
    def factorisation(self):
        return self.system.factorisation

    @property
    def fixed(self):
        return self.system.fixed

    def _image_operators(self, rest_at, mapped_ids):
        """The mapped triangles' share: their images' gradients (deformation.
        corner_gradient_operators) pulled into the right-hand side, and the edge differences
        their images' 4th vertices need."""
        corners = self.system.triangles[mapped_ids]
        edges, normal = deformation.corner_gradient_operators(rest_at, corners)
        self.from_moves = self.system.pulled(edges, mapped_ids)             # (N x n)
        self.from_offsets = self.system.pulled(normal, mapped_ids)          # (N x m)
        self.image_corners = np.ascontiguousarray(corners.T)                # (3, m)
        # the images' rest edges v2 - v1, v3 - v1, coordinate first (3, m)
        self.rest_image_edges = [np.ascontiguousarray((rest_at[ends] - rest_at[corners[:, 0]]).T)
                                 for ends in (corners[:, 1], corners[:, 2])]

    def _straddle_checks(self, rest_at, source_triangles, vertex_map):
        """What the STRADDLE check needs: the images' rest edges' Gram matrices and the source
        triangles under each mapped triangle's corners."""
        self.rest_at = rest_at
        self.rest_image_gram = _gram(*self.rest_image_edges, axis=0)           # (3, m)
        self.under = source_triangles[
            vertex_map.triangle[self.system.triangles[self.mapped_ids]]]            # (m, 3, 3)

    def _pair_operators(self, source_triangles, pairs, weights, paired_ids):
        """The paired triangles' share: the source triangles they use, and the weighted mean of
        those triangles' stacked gradients pulled into the right-hand side."""
        rows = pairs[paired_ids]
        used = np.unique(rows.indices)
        self.used_source_triangles = source_triangles[used]
        self.used_source_inverses = deformation.corner_inverses(
            self.source_rest[self.used_source_triangles])
        mean = sp.diags(1.0 / weights[paired_ids]) @ rows[:, used]
        self.paired_row = np.full(len(weights), -1)
        self.paired_row[paired_ids] = np.arange(len(paired_ids))
        self.pair_mean = mean.tocsr()
        self.from_source_gradients = self.system.pulled(sp.kron(mean, sp.identity(3)), paired_ids) \
            if len(used) else None

    def __call__(self, deltas, correction=None):
        """(E, n, 3) target displacements of source deltas (E, n_s, 3) (in the target's frame).
        correction: optional callable(displacements (B, n, 3), the block's source deltas
        (B, n_s, 3)) -> (B, n, 3), applied to each block."""
        out = np.empty((len(deltas), self.system.n, 3))
        for block in blocks(len(deltas)):
            out[block] = self._solved_block(deltas[block])
        self._stretch_bounded(out, deltas)
        untangled = self._untangled(out, deltas)
        if len(untangled):      # the local solves may stretch an edge past the bound again
            changed = out[untangled]
            self._stretch_bounded(changed, deltas[untangled])
            out[untangled] = changed
        if correction is not None:
            for block in blocks(len(deltas)):
                out[block] = correction(out[block], deltas[block])
        return out

    def _solved_block(self, deltas):
        """(B, n, 3) the displacements of B source expressions' deltas (B, n_s, 3)."""
        moves = self.sampling @ as_columns(deltas)                             # (n, 3B)
        return as_rows(self.system.solved(self._right_hand_side(deltas, moves), moves[self.anchors],
                                          self.anchors))

    def _right_hand_side(self, deltas, moves):
        """(N, 3B) for B expressions' deltas (B, n_s, 3) and their moves at the target vertices."""
        b = len(deltas)
        rhs = np.repeat(self.constant, b, axis=1)
        rhs += self.from_moves @ moves
        offsets, stretch = self._image_offsets(moves, b)
        rhs += self.from_offsets @ offsets
        if self.from_source_gradients is not None:
            gradients = deformation.deformed_gradients(
                self.used_source_inverses, (self.source_rest + deltas)[:, self.used_source_triangles])
            rhs += self.from_source_gradients @ as_columns(deformation.stack_gradients(gradients))
        ids, expression, wanted, image = self._straddling(deltas, moves, stretch)
        self._goals_changed(rhs, self.mapped_ids[ids], expression, wanted - image, len(deltas))
        return rhs

    def _straddling(self, deltas, moves, stretch):
        """The straddling images (STRADDLE): (their ids among the mapped triangles (F,), their
        expressions (F,), the mean gradient of the source triangles under their triangles' three
        corners (F, 3, 3), which they take instead of their images' own (F, 3, 3)); stretch
        (m, B): the images' own."""
        ids, expression = np.nonzero(stretch > STRADDLE)       # the limit is at least STRADDLE
        ids, expression, wanted = self._straddlers(ids, expression, stretch[ids, expression],
                                                   deltas)
        return ids, expression, wanted, self._image_gradients(ids, expression, moves)

    def _straddlers(self, ids, expression, stretch, deltas):
        """_straddling's first three among mapped triangles ids (F,) in expressions (F,) whose
        images stretch (F,) more than STRADDLE."""
        rest_sources = self.source_rest[self.under[ids]]                         # (F, 3, 3, 3)
        sources = rest_sources + deltas[expression[:, None, None], self.under[ids]]
        under = _largest_stretch(_gram(*deformation.corner_edges(rest_sources)),
                                 _gram(*deformation.corner_edges(sources)))      # (F, 3)
        straddling = stretch > STRADDLE * np.maximum(under.max(axis=1), 1.0)
        rest_sources, sources = rest_sources[straddling], sources[straddling]
        wanted = deformation.corner_gradients(rest_sources, sources).mean(axis=1)
        return ids[straddling], expression[straddling], wanted

    def _image_gradients(self, ids, expression, moves, inverses=None, vertex_rows=None):
        """(F, 3, 3) the gradients of the images of mapped triangles ids (F,) (among the mapped)
        in expressions (F,) of the block whose moves at the target vertices are moves (n, 3B);
        inverses: their rest images' deformation.corner_inverses (F, 3, 3), if made already;
        vertex_rows (n,): each target vertex's row of moves, where moves are not all of them."""
        corners = self.system.triangles[self.mapped_ids[ids]]                    # (F, 3)
        rest = self.rest_at[corners]
        if inverses is None:
            inverses = deformation.corner_inverses(rest)
        rows = corners if vertex_rows is None else vertex_rows[corners]
        return deformation.deformed_gradients(
            inverses, rest + as_rows(moves)[expression[:, None], rows])

    def _goals_changed(self, rhs, triangle_ids, expression, change_gradients, b):
        """rhs (N, 3B) with the goals of target triangles triangle_ids (F,) in expressions
        (F,) of the block of b changed by change_gradients (F, 3, 3) (their weights applied)."""
        if not len(triangle_ids):
            return
        rows = (3 * np.asarray(triangle_ids)[:, None] + np.arange(3)).ravel()
        change = np.zeros((len(rows), 3 * b))
        stacked = self.system.given_rows_weight[rows, None] * \
            deformation.stack_gradients(change_gradients)                        # (3F, 3)
        for axis in range(3):          # each coordinate's column of its expression
            change[np.arange(len(rows)), axis * b + np.repeat(expression, 3)] = stacked[:, axis]
        # these rows of G reach only their triangles' own unknowns: update those alone
        own = self.system.grad[rows]
        unknowns = np.unique(own.indices)
        rhs[unknowns] += own[:, unknowns].T @ change

    def _bound_checks(self, source_triangles, vertex_map, weights):
        """What STRETCH_BOUND needs: the target's edges with an image at both ends (their ends'
        ids) and their images as sparse differences of the source's vertices (through the
        vertex map's closest points, valid or not, as expression_measures reads them), their
        rest vectors and lengths, and which triangles hold each vertex."""
        triangles = self.system.triangles
        imaged = np.flatnonzero(vertex_map.triangle >= 0)
        image_sampling = _barycentric_sampling(vertex_map, source_triangles, imaged,
                                               self.system.n, len(self.source_rest))
        has_image = np.zeros(self.system.n, dtype=bool)
        has_image[imaged] = True
        n = self.system.n
        edges = unique_edges(triangles)
        self.bound_edges = edges[has_image[edges].all(axis=1)]
        self.bound_ends = np.ascontiguousarray(self.bound_edges.T)       # (lower, higher) ids
        k = len(self.bound_edges)
        edge_difference = sp.csr_matrix(
            (np.tile([-1.0, 1.0], k), (np.repeat(np.arange(k), 2), self.bound_edges.ravel())),
            shape=(k, n))
        self.image_edge_difference = (edge_difference @ image_sampling).tocsr()
        self.image_sampling = image_sampling
        self.imaged_triangles = has_image[triangles].all(axis=1)
        self.corner_ids = np.ascontiguousarray(triangles.T)            # (3, T) for _turned
        self.rest_edges = edge_difference @ self.system.rest_vertices                 # (k, 3)
        self.rest_lengths = np.linalg.norm(self.rest_edges, axis=1)
        # the length past which an edge may pass STRETCH_BOUND, less a margin far beyond rounding
        self.bound_lengths = STRETCH_BOUND * (1 - 1e-9) * self.rest_lengths
        self.squared_bound_lengths = self.bound_lengths ** 2
        self.image_rest_edges = self.image_edge_difference @ self.source_rest         # (k, 3)
        t = len(triangles)
        self.vertex_triangles = sp.csr_matrix(
            (np.ones(3 * t), (triangles.ravel(), np.repeat(np.arange(t), 3))), shape=(self.system.n, t))
        self.covered = np.asarray(weights) > 0
        self.mapped_index = np.full(t, -1)             # each target triangle's row among the mapped
        self.mapped_index[self.mapped_ids] = np.arange(len(self.mapped_ids))

    def _stretch_bounded(self, out, deltas):
        """out (E, n, 3), the displacements of source deltas (E, n_s, 3), with the goals around
        every edge an expression stretches more than STRETCH_BOUND beyond its image capped, the
        same triangles for every expression (so that expressions added together, jawOpen and
        mouthClose, still undo each other there); the region grows by a ring of triangles a
        round while the worst passing edge gives way, for at most BOUND_ROUNDS rounds."""
        passing = np.zeros((len(deltas), self.system.n), dtype=bool)
        worst = np.zeros(len(deltas))
        # a bound on each edge's length in each block's expressions, grown by what each round
        # changes: the rounds' checks measure only the edges it lets pass STRETCH_BOUND
        longest = np.zeros((len(blocks(len(deltas))), len(self.bound_edges)))
        self._check(out, deltas, np.arange(len(deltas)), passing, worst, longest, False)
        lower, higher = self.bound_ends
        share = min((worst.max(initial=1.0) - STRETCH_BOUND) / BOUND_FADE, 1.0)
        region = np.zeros(self.system.n, dtype=bool)
        capped = np.zeros(len(self.covered), dtype=bool)
        for _ in range(BOUND_ROUNDS):
            if not passing.any():
                break
            was = worst.copy()
            region |= passing.any(axis=0)
            around = (self.vertex_triangles.T @ region.astype(np.float64)) > 0       # (T,)
            added = np.flatnonzero(around & ~capped & self.covered)
            if not len(added):                # every triangle around the passing edges is capped
                break
            capped |= around
            triangles, expression, change = self._capping_changes(deltas, added, share)
            for bound, block in zip(longest, blocks(len(deltas))):
                these = (expression >= block.start) & (expression < block.stop)
                if not these.any():
                    continue
                which, solved = self._solved_change(
                    triangles[these], expression[these] - block.start, change[these],
                    block.stop - block.start)
                out[block][which] += solved
                grown = np.zeros(self.system.n)        # each vertex's largest change
                for moved in solved:
                    np.maximum(grown, np.sqrt(np.einsum("vi,vi->v", moved, moved)), out=grown)
                bound += grown[lower] + grown[higher]    # an edge grows by at most its ends' moves
            self._check(out, deltas, np.unique(expression), passing, worst, longest, True)
            # on while a passing expression's worst edge gives way, a ring of triangles further
            if not (worst < GIVING_WAY * was)[was > STRETCH_BOUND].any():
                break
            region = (self.vertex_triangles @ around.astype(np.float64)) > 0

    @cached_property
    def _turn_references(self):
        """((T, 3) the target triangles' rest normals, (n, 3) the source at each target vertex's
        closest point (the bound's images), (T, 3) those images' rest normals, (T x T) the
        triangles beside each other): what _untangled needs, made when first needed."""
        triangles = self.system.triangles
        image_rest = self.image_sampling @ self.source_rest
        return (triangle_normals(self.system.rest_vertices, triangles), image_rest,
                triangle_normals(image_rest, triangles), deformation.triangle_adjacency(triangles))

    def _untangled(self, out, deltas):
        """out (E, n, 3), the displacements of source deltas (E, n_s, 3), with each expression's
        tangles undone (TANGLED_WEIGHT); returns the ids of the expressions changed."""
        changed = []
        for block in blocks(len(out)):
            for expression, turned in zip(range(block.start, block.stop), self._turned(out[block])):
                if self._untangle_expression(out[expression], deltas[expression], turned):
                    changed.append(expression)
        return np.asarray(changed, dtype=np.int64)

    def _turned(self, displacements):
        """[(k,) per expression]: the imaged target triangles displacements (B, n, 3) turn over,
        their moved normals made coordinate first (as _images: several times faster than
        gathering (T, 3, 3) corners per expression), a few thousand triangles at a time (their
        temporaries stay in cache; all at once they added 57 MiB to the 50k clone's peak)."""
        positions = np.ascontiguousarray(np.transpose(displacements, (2, 1, 0)))   # (3, n, B)
        positions += self.system.rest_vertices.T[:, :, None]
        rest_normals = self._turn_references[0]
        over = np.zeros((len(rest_normals), len(displacements)), dtype=bool)
        for rows in blocks(len(rest_normals), TRIANGLES_PER_CHUNK):
            first, second, third = self.corner_ids[:, rows]
            origin = np.take(positions, first, axis=1)
            ends = [np.take(positions, corner, axis=1) - origin for corner in (second, third)]
            normals = np.stack([ends[0][(k + 1) % 3] * ends[1][(k + 2) % 3] -
                                ends[0][(k + 2) % 3] * ends[1][(k + 1) % 3] for k in range(3)],
                               axis=-1)                                              # (t, B, 3)
            over[rows] = turned_over(rest_normals[rows, None], normals)
        over &= self.imaged_triangles[:, None]
        return [np.flatnonzero(column) for column in over.T]

    def _untangle_expression(self, displacements, delta, turned):
        """displacements (n, 3) of source delta (n_s, 3) with their tangles undone, round by
        round (_untangle); turned: the imaged triangles they turn over. Whether any was."""
        triangles, rest = self.system.triangles, self.system.rest_vertices
        rest_normals = self._turn_references[0]
        untangled = False
        for _ in range(UNTANGLE_ROUNDS):
            tangled, image_turn = self._tangles(turned, delta)
            if not len(tangled):
                break
            touched = self._untangle(displacements, tangled, image_turn)
            untangled = True
            # only the triangles the solve moved can have turned over or back
            touched = touched[self.imaged_triangles[touched]]
            turned = np.union1d(np.setdiff1d(turned, touched), touched[turned_over(
                rest_normals[touched],
                triangle_normals(rest + displacements, triangles[touched], False))])
        return untangled

    def _tangles(self, turned, delta):
        """(the tangles among imaged target triangles turned (k,) that source delta (n_s, 3)
        turns over: those whose images turn over neither themselves nor beside them, (t,)
        their images' turns (radians))."""
        if not len(turned):
            return turned, np.zeros(0)
        _, image_rest, image_normals, beside = self._turn_references
        near = beside[turned]
        seen = np.union1d(turned, near.indices)             # the turned and those beside them
        corners = self.system.triangles[seen]
        vertices, at = np.unique(corners, return_inverse=True)
        moved = image_rest[vertices] + self.image_sampling[vertices] @ delta
        image_moved = triangle_normals(moved, at.reshape(corners.shape))
        turning = np.zeros(len(self.system.triangles), dtype=bool)
        turning[seen] = self.imaged_triangles[seen] & turned_over(image_normals[seen],
                                                                  image_moved)
        own = ~turning[turned] & ~source_turns_beside(turning, near)
        rows = np.searchsorted(seen, turned[own])
        return turned[own], _angles(image_normals[turned[own]], image_moved[rows])

    def _untangle(self, displacements, tangled, image_turn):
        """displacements (n, 3) with the corners of target triangles tangled (k,) and a ring of
        triangles around them solved again: every triangle they touch keeps its solved gradient
        as its goal, except the tangled ones, whose solved gradients turn back to their images'
        turns image_turn (k,) and weigh TANGLED_WEIGHT. Fixed vertices and the rest stay.
        Returns the triangles the solve may have moved (those touching what it solved)."""
        triangles, rest = self.system.triangles, self.system.rest_vertices
        # looked up among the rows of the vertices concerned alone: a product with the whole
        # vertex_triangles took most of a small untangling's time at 50k vertices
        around = np.unique(self.vertex_triangles[np.unique(triangles[tangled])].indices)
        inside = np.setdiff1d(triangles[around], self.system.fixed)
        touching = np.unique(self.vertex_triangles[inside].indices)
        if not len(inside):
            return touching
        # the reduced operator whatever the system's formulation: the displacements hold no
        # 4th vertices
        gradient = deformation.gradient_operator(rest, triangles[touching])[0].tocsc()
        positions = rest + displacements
        goals = (gradient @ positions).reshape(len(touching), 3, 3)              # F^T blocks
        at = np.searchsorted(touching, tangled)
        rest_normals = self._turn_references[0][tangled]
        normals = triangle_normals(positions, triangles[tangled])
        axes = np.cross(normals, rest_normals)
        lengths = np.linalg.norm(axes, axis=1, keepdims=True)
        axes = np.divide(axes, lengths, out=np.zeros_like(axes), where=lengths > 0)
        back = Rotation.from_rotvec(
            axes * (_angles(normals, rest_normals) - image_turn)[:, None]).as_matrix()
        goals[at] = goals[at] @ np.transpose(back, (0, 2, 1))                  # (R F)^T
        weights = np.ones(len(touching))
        weights[at] = TANGLED_WEIGHT
        weights = np.repeat(weights, 3)
        held = displacements.copy()
        held[inside] = 0.0
        inner = gradient[:, inside]
        # whispered as the system's normal matrix: a region that is a whole part stays definite
        _, solve = factorised(whispered((inner.T @ sp.diags(weights) @ inner).tocsc()))
        target = goals.reshape(-1, 3) - gradient @ (rest + held)
        displacements[inside] = solve(inner.T @ (weights[:, None] * target))
        return touching

    def _capping_changes(self, deltas, ids, share):
        """What moving the goals of covered target triangles ids (F,) the share (0-1] of the way
        to their caps (their rotations kept) changes in them, where a goal stretches more than
        STRETCH_BOUND in an expression of deltas (E, n_s, 3): (the triangles (C,), their
        expressions (C,), the goals' changes (C, 3, 3)), triangle by triangle in the order of
        ids, expression by expression within a triangle. Every expression at once, from the
        source's moves sampled at the triangles' corners alone."""
        mapped = self.mapped_index[ids] >= 0
        corners = self.system.triangles[ids[mapped]]
        inverses = np.zeros((len(ids), 3, 3))
        inverses[mapped] = deformation.corner_inverses(self.rest_at[corners])
        vertices = np.unique(corners)
        vertex_rows = np.full(self.system.n, -1)
        vertex_rows[vertices] = np.arange(len(vertices))
        e = len(deltas)
        sampling = self.sampling[vertices]
        used = np.unique(sampling.indices)                  # the source vertices it reads
        moves = sampling[:, used] @ as_columns(deltas[:, used])                 # (v, 3E)
        triangles, expression = np.repeat(ids, e), np.tile(np.arange(e), len(ids))
        goals = self._goals(triangles, expression, deltas, moves, self._straddling_among(
            triangles, deltas, moves, vertex_rows), np.repeat(inverses, e, axis=0), vertex_rows)
        capped = _singular_values_capped(goals, STRETCH_BOUND)
        changed = np.abs(capped - goals).max(axis=(1, 2), initial=0.0) > 0
        return triangles[changed], expression[changed], share * (capped - goals)[changed]

    def _solved_change(self, triangles, expression, change, b):
        """((B',) the expressions of a block of b whose goals on target triangles (C,), C > 0,
        change by change (C, 3, 3) in expressions (C,) of the block, (B', n, 3) what that changes
        in their displacements). The solve is linear in its right-hand side and the parts'
        translations in the displacements, so the change is solved alone."""
        which, expression = np.unique(expression, return_inverse=True)
        # the right-hand side of those expressions alone
        rhs = np.zeros((self.system.grad.shape[1], 3 * len(which)))
        self._goals_changed(rhs, triangles, expression, change, len(which))
        return which, as_rows(self.system.solved(
            rhs, np.zeros((len(self.anchors), 3 * len(which))), self.anchors))

    def _straddling_among(self, triangles, deltas, moves, vertex_rows):
        """_straddling's first three of the mapped ones among target triangles (F,); moves
        (v, 3E) at the target vertices of vertex_rows (n,) (_capping_changes)."""
        rows = self.mapped_index[triangles]
        rows = np.unique(rows[rows >= 0])
        images = self._images(_coordinate_first(moves, len(deltas)), rows, vertex_rows)
        stretch = _largest_stretch(self.rest_image_gram[:, rows, None], _gram(*images, axis=0))
        which, expression = np.nonzero(stretch > STRADDLE)
        return self._straddlers(rows[which], expression, stretch[which, expression], deltas)

    def _check(self, out, deltas, ids, passing, worst, longest, bounded):
        """passing (E, n) and worst (E,) of the expressions ids (_passing_vertices) updated from
        their displacements out (E, n, 3) and source deltas (E, n_s, 3). longest (blocks of E,
        k): a bound on each edge's length in each block's expressions. Not bounded: ids are
        every expression, in order, and longest is made; bounded: only the edges it lets pass
        their bound_lengths are measured."""
        for block in blocks(len(ids)):
            chosen = ids[block] if bounded else block       # every expression: a view of each block
            edges = np.flatnonzero(
                (longest[np.unique(chosen // EXPRESSIONS_PER_BLOCK)] > self.bound_lengths).any(
                    axis=0)) if bounded else None
            passing[chosen], worst[chosen], made = self._passing_vertices(
                out[chosen], deltas[chosen], edges)
            if not bounded:
                longest[block.start // EXPRESSIONS_PER_BLOCK] = made

    def _passing_vertices(self, displacements, deltas, edges=None):
        """((B, n) bool, (B,), (k,) or None): the ends of the edges displacements (B, n, 3)
        stretch more than STRETCH_BOUND beyond their images under the source's deltas
        (B, n_s, 3), and each expression's worst excess stretch (1 where no edge stretches past
        the bound), among the bound's edges `edges` if given, else among all of them: then a
        bound on each edge's length in these expressions too."""
        b = len(deltas)
        rest = self.rest_lengths
        lower, higher = self.bound_ends
        # the edges' moves taken coordinate first (as _images), a few thousand edges at a time
        # so that their temporaries stay in cache: several times faster than a sparse
        # difference of all of them
        moves = np.ascontiguousarray(np.transpose(displacements, (2, 1, 0)))      # (3, n, B)
        if edges is None:
            # an edge grows by at most its ends' moves: only where those (the block's largest)
            # reach STRETCH_BOUND - 1 rest lengths (less a margin far beyond rounding) can it
            # stretch past
            reach = np.sqrt(_row_largest(components_dot(moves, moves)))             # (n,)
            reach = reach[lower] + reach[higher]                                     # (k,)
            longest = rest + reach
            near = np.flatnonzero(reach > (STRETCH_BOUND - 1) * (1 - 1e-9) * rest)
        else:
            longest, near = None, edges
        edges, stretched = [np.zeros(0, dtype=np.int64)], [np.zeros((0, b))]
        for rows in blocks(len(near), EDGES_PER_CHUNK):
            ids = near[rows]
            squared = _squared_lengths(
                self.rest_edges[ids], (np.take(coordinate, higher[ids], axis=0) -
                                       np.take(coordinate, lower[ids], axis=0)
                                       for coordinate in moves))
            largest = _row_largest(squared)
            if longest is not None:
                longest[ids] = np.sqrt(largest)
            # the image's stretch counts from 1, so only an edge stretched past the bound can
            # pass: the lengths of those whose largest square passes the bound length's alone
            candidate = largest > self.squared_bound_lengths[ids]
            ids, lengths = ids[candidate], np.sqrt(squared[candidate])
            past = (lengths > STRETCH_BOUND * rest[ids, None]).any(axis=1)
            edges.append(ids[past])
            stretched.append(lengths[past])
        edges = np.concatenate(edges)
        excess = excess_stretches(
            rest[edges, None], np.concatenate(stretched),
            np.linalg.norm(self.image_rest_edges[edges], axis=1)[:, None],
            _lengths(self.image_rest_edges[edges],
                     (self.image_edge_difference[edges] @ as_columns(deltas)).reshape(
                         len(edges), 3, b).transpose(1, 0, 2)))
        passing = np.zeros((b, self.system.n), dtype=bool)
        edge, expression = np.nonzero(excess > STRETCH_BOUND)
        passing[np.repeat(expression, 2), self.bound_edges[edges[edge]].ravel()] = True
        return passing, excess.max(axis=0, initial=1.0), longest

    def _goals(self, ids, expression, deltas, moves, straddled, inverses, vertex_rows):
        """(F, 3, 3) the gradients covered target triangles ids (F,) are given in expressions
        (F,) of the block: their images' (a straddling one's replacement), or their pairs'
        weighted mean. inverses (F, 3, 3): the mapped ones' rest images' corner_inverses;
        moves (v, 3B) at the target vertices of vertex_rows (n,)."""
        goals = np.empty((len(ids), 3, 3))
        mapped_index = self.mapped_index
        mapped = mapped_index[ids] >= 0
        goals[mapped] = self._image_gradients(mapped_index[ids[mapped]], expression[mapped], moves,
                                              inverses[mapped], vertex_rows)
        straddle_ids, straddle_expression, wanted = straddled
        key = mapped_index[ids] * len(deltas) + expression
        straddle_key = straddle_ids * len(deltas) + straddle_expression
        replaced = mapped & np.isin(key, straddle_key)
        order = np.argsort(straddle_key)
        goals[replaced] = wanted[order[np.searchsorted(straddle_key[order], key[replaced])]]
        paired = ~mapped
        if paired.any():
            rows, at = np.unique(self.paired_row[ids[paired]], return_inverse=True)
            rows = self.pair_mean[rows]
            used = np.unique(rows.indices)
            corners = self.used_source_triangles[used]
            gradients = deformation.deformed_gradients(                         # (B, U, 3, 3)
                self.used_source_inverses[used], self.source_rest[corners] + deltas[:, corners])
            # each triangle's mean in every expression at once (p, B * 9)
            means = rows[:, used] @ np.moveaxis(gradients, 0, 1).reshape(len(used), -1)
            goals[paired] = means.reshape(len(rows.indptr) - 1, len(deltas), 3, 3)[
                at.ravel(), expression[paired]]
        return goals

    def _image_offsets(self, moves, b):
        """(m, 3B) the 4th-vertex offsets of the mapped triangles' deformed images, and (m, B)
        their largest stretch within their planes."""
        m = len(self.mapped_ids)
        offsets = np.empty((m, 3, b))
        stretch = np.empty((m, b))
        moves = _coordinate_first(moves, b)
        # a few thousand triangles at a time: the cross product's temporaries stay in cache, and
        # the images' edges are made for those alone (all of them, (m, 3B) twice, were the
        # largest arrays of a block)
        for rows in blocks(m, TRIANGLES_PER_CHUNK):
            images = self._images(moves, rows)
            offsets[rows] = np.moveaxis(deformation.fourth_offsets(*images, axis=0), 0, 1)
            stretch[rows] = _largest_stretch(self.rest_image_gram[:, rows, None],
                                             _gram(*images, axis=0))
        return offsets.reshape(m, 3 * b), stretch

    def _images(self, moves, rows, vertex_rows=None):
        """The two deformed edges (3, r, B) of the mapped triangles rows' images, from the
        sampled moves coordinate first (3, n, B: _coordinate_first); vertex_rows (n,): each
        target vertex's row of moves, where moves are not all of them."""
        corners = self.image_corners[:, rows]
        first, second, third = corners if vertex_rows is None else vertex_rows[corners]
        # np.take: several times faster than fancy indexing on a middle axis
        origin = np.take(moves, first, axis=1)
        images = []
        for ends, rest in zip((second, third), self.rest_image_edges):
            edges = np.take(moves, ends, axis=1) - origin
            edges += rest[:, rows, None]
            images.append(edges)
        return images


def _coordinate_first(moves, b):
    """(n, 3B) moves as (3, n, B): the images' edges, the cross product and the Gram entries
    made from them all run on contiguous (triangles, B) arrays, one per coordinate."""
    return np.ascontiguousarray(moves.reshape(len(moves), 3, b).transpose(1, 0, 2))


def _lengths(rest, moved):
    """(k, B) the lengths of edges (k, 3) at rest plus their moves (k, B) per coordinate (3 of
    them, changed in place: they are made for this)."""
    squared = _squared_lengths(rest, moved)
    return np.sqrt(squared, out=squared)


def _squared_lengths(rest, moved):
    """_lengths squared."""
    squared = None
    for axis, move in enumerate(moved):
        move += rest[:, axis, None]
        move *= move
        if squared is None:
            squared = move
        else:
            squared += move
    return squared


def whispered(normal):
    """A sparse normal matrix with a whisper of regularisation (1e-10 of its mean diagonal):
    definite where a whole part's translation is free."""
    eps = 1e-10 * normal.diagonal().mean()
    return (normal + eps * sp.identity(normal.shape[0], format="csc")).tocsc()


def _angles(first, second):
    """(k,) the angles (radians) between unit vectors first and second (k, 3)."""
    return np.arccos(np.clip(np.einsum("ki,ki->k", first, second), -1.0, 1.0))


def _row_largest(values):
    """(k,) the largest of each row of values (k, B), B >= 1: column by column, several times
    faster than a reduction over so short an axis."""
    largest = values[:, 0].copy()
    for column in values.T[1:]:
        np.maximum(largest, column, out=largest)
    return largest


def _gram(first, second, axis=-1):
    """(3, ...) the Gram matrices' entries (e1.e1, e1.e2, e2.e2) of edge pairs (xyz along axis)."""
    first, second = np.moveaxis(first, axis, 0), np.moveaxis(second, axis, 0)
    # coordinate by coordinate: np.sum over a strided axis of 3 took 1.6x the time
    return np.stack([components_dot(first, first), components_dot(first, second),
                     components_dot(second, second)])


def _largest_stretch(rest, deformed):
    """The largest singular value of the map taking triangles' rest edges to deformed ones
    within their planes, from the Gram matrices' entries (3, ...) of each: the square root of
    the larger root of det(D - s R) = 0. A degenerate rest triangle (its edges within 1e-6
    radians of parallel) reads 0: it has no plane to stretch in."""
    r11, r12, r22 = rest
    d11, d12, d22 = deformed
    area = r11 * r22 - r12 * r12
    with np.errstate(divide="ignore", invalid="ignore"):
        half_trace = (r22 * d11 - 2 * r12 * d12 + r11 * d22) / (2 * area)
        determinant = (d11 * d22 - d12 * d12) / area
        largest = half_trace + np.sqrt(np.maximum(half_trace * half_trace - determinant, 0.0))
    return np.where(area > 1e-12 * r11 * r22, np.sqrt(np.maximum(largest, 0.0)), 0.0)


def _singular_values_capped(gradients, cap):
    """gradients (F, 3, 3) with their singular values capped at `cap` (their rotations kept);
    those within it exactly as they are."""
    capped = gradients.copy()
    # the largest singular value is at most the Frobenius norm: only gradients whose norm
    # passes the cap (less a margin far beyond rounding) are decomposed
    near = np.flatnonzero(np.einsum("fij,fij->f", gradients, gradients) > cap * cap * (1 - 1e-6))
    left, values, right = np.linalg.svd(gradients[near])
    over = values.max(axis=1, initial=0.0) > cap
    capped[near[over]] = (left[over] * np.minimum(values[over], cap)[:, None, :]) @ right[over]
    return capped


def _barycentric_sampling(vertex_map, source_triangles, ids, n_target, n_source):
    """Sparse (n_target x n_source): per-source-vertex values at the target vertices `ids` by
    the vertex map's barycentric coordinates (rows of the other vertices are 0)."""
    corners = source_triangles[vertex_map.triangle[ids]]                     # (k, 3)
    return sp.csr_matrix((vertex_map.bary[ids].ravel(), (np.repeat(ids, 3), corners.ravel())),
                         shape=(n_target, n_source))


def blocks(count, size=EXPRESSIONS_PER_BLOCK):
    """Slices of `count` expressions, `size` at a time."""
    return [slice(start, min(start + size, count)) for start in range(0, count, size)]


def as_columns(values):
    """(B, k, 3) per-expression vectors -> (k, 3B), the solve's layout: column xyz * B + e
    (each coordinate's B columns side by side)."""
    columns = np.ascontiguousarray(np.transpose(values, (1, 2, 0)))
    return columns.reshape(values.shape[1], 3 * len(values))     # not -1: k may be 0


def as_rows(columns):
    """(k, 3B) in the solve's layout -> (B, k, 3)."""
    b = columns.shape[1] // 3                 # given, not -1: k may be 0
    return np.transpose(columns.reshape(len(columns), 3, b), (2, 0, 1))


def _checked_fixed(fixed, n_vertices):
    """The fixed vertex ids as a sorted unique int array, or ExCloneError if one is no vertex."""
    fixed = np.unique(np.asarray(fixed, dtype=np.int64).ravel())
    if len(fixed) and (fixed[0] < 0 or fixed[-1] >= n_vertices):
        raise ExCloneError(f"fixed vertex ids must lie in [0, {n_vertices}); got "
                           f"{fixed[0]}..{fixed[-1]}")
    return fixed
