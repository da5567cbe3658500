"""Positional goals at the rims of the eye openings (docs/method.md §8, "Rims").

Deformation transfer carries gradients, not positions: a lid whose skin is taller or shorter
than the source's turns by the source's gradients and travels a fraction of the way (the
library's blink left 16% of the demo head's open height). Closing an eye is a positional goal.

So after the transfer each eye's lid rows (the visible lid edges the measures read,
core.expression_measures) get a soft target: every rim vertex keeps its transferred motion
across and along the face, and its motion along the face's up becomes the source's at its
corresponding point (the vertex map), where the registration put it. The rest of the face
follows by least squares on the transfer's own gradient term:

    min_c  sum_t w_t ||G_t c||^2 + RIM_WEIGHT / h^2 sum_rims ||d_i + c_i - g_i||^2

(d the transfer's solution, h the target's mean edge length). Because d minimises the gradient
term already, d + c is exactly the solution of the transfer with the positional term added.
The goals are linear in the source's deltas, so a sum of expressions is corrected as the sum of
its parts.

The travel is not scaled by the two openings' heights: scaling by the ratio of the rows' rest
gaps left 11-14% of the demo head's opening at eyeBlink (its images' gap is larger than its
own) and made new ICT identities overshoot (ICT's expressions are the same deltas on every
identity); unscaled, the demo head closes to 2% and 5% (docs/method.md §13).
"""
import numpy as np
import scipy.sparse as sp

from . import expression_measures
from .transfer import EXPRESSIONS_PER_BLOCK, as_columns, as_rows, blocks

# Weight of a rim vertex's goal per unit of squared target edge length: strong enough that the
# rims reach their goals within a few percent of the lid's travel, soft enough that a rim vertex
# with a poor image cannot tear the lid.
RIM_WEIGHT = 100.0

class RimGoals:
    """The eyes' rim rows on the welded target region, and the factorised correction."""

    def __init__(self, region, source_triangles, landmark_names, landmark_ids, vertex_map,
                 transfer):
        """region: surface.Surface of the target triangles the transfer solves (welded numbering);
        source_triangles: the source region's triangles (welded numbering); landmark_names/ids:
        the fit's target landmarks (welded ids); vertex_map: the fit's correspondence.VertexMap;
        transfer: the fit's transfer.Transfer (its gradient operator and weights)."""
        openings = expression_measures.Openings(
            region.vertices, region.triangles,
            {str(name): int(i) for name, i in zip(landmark_names, landmark_ids)})
        self.eyes = [eye for eye in (_EyeRims(lids, vertex_map.valid)
                                     for lids in openings.lids.values()) if eye.usable]
        self.ids = np.concatenate([eye.ids for eye in self.eyes]) if self.eyes \
            else np.zeros(0, dtype=np.int64)
        self.images = _Images(vertex_map, source_triangles, self.ids)
        self.solve = _Correction(transfer, self.ids, RIM_WEIGHT / region.mean_edge_length ** 2) \
            if len(self.ids) else None

    def __call__(self, result, source_deltas):
        """The transferred displacements `result` (E, n, 3) with the rims brought to their goals;
        source_deltas (E, n_source, 3): the expressions on the aligned source."""
        if self.solve is None:
            return result
        moves_at = self.images.at(source_deltas)                                # (E, k, 3)
        goals, start = [], 0
        for eye in self.eyes:
            mine = slice(start, start + len(eye.ids))
            goals.append(eye.goals(result, moves_at[:, mine]))
            start = mine.stop
        goals = np.concatenate(goals, axis=1)                                   # (E, k, 3)
        return result + self.solve(goals - result[:, self.ids])


class _Images:
    """The source at the corresponding points (the vertex map) of the target's rim vertices."""

    def __init__(self, vertex_map, source_triangles, ids):
        self.vertex_map, self.source_triangles, self.ids = vertex_map, source_triangles, ids

    def at(self, values):
        """(E, k, 3) per-source-vertex values (E, n_source, 3) at the rim vertices' images."""
        return np.moveaxis(self.vertex_map.sample(np.moveaxis(values, 0, 1),
                                                  self.source_triangles, self.ids), 1, 0)


class _EyeRims:
    """One eye's mapped rim vertices (its upper and lower lid rows) and the face's up."""

    def __init__(self, lids, mapped):
        """lids: expression_measures' lids of the eye on the rest target; mapped: (n,) bool,
        the target vertices with an image on the source."""
        self.up = lids.opening.up
        self.ids = np.concatenate([row[mapped[row]] for row in (lids.upper, lids.lower)])
        self.usable = min(mapped[row].sum() for row in (lids.upper, lids.lower)) >= 2

    def goals(self, result, images_moves):
        """(E, k, 3): each rim vertex's transferred motion with its motion along the face's up
        replaced by its image's on the source (images_moves (E, k, 3))."""
        moved = result[:, self.ids]
        return moved + (images_moves @ self.up - moved @ self.up)[..., None] * self.up


class _Correction:
    """The correction c of the module docstring, on the transfer's own factorisation: made with
    one back-substitution column per rim vertex, then one back-substitution per call.

    With A = G^T W G (the transfer's normal matrix), p the pull, S the rows of the rim vertices
    and r their offsets, c solves (A + p S^T S) c = p S^T r. A is singular only by each connected
    part's translation (the transfer regularises it by a whisper, see core.transfer), so on the
    parts that hold a rim and no fixed vertex c = u + T t: T those parts' translations, u = A^+ f
    the zero-mean answer to balanced forces f = S^T y, and the pulls y (k) and translations t
    solve the small saddle system (Woodbury's identity with the translations split off)

        [ I/p + S A^+ S^T   S T ] [y]   [r]
        [ (S T)^T           0   ] [t] = [0]

    A second factorisation of A + p S^T S gives the same c (to 1e-7 of the diagonal at 50k
    target vertices) but costs more: 0.5-0.7 CPU-s to make and 19 MiB held there, against
    0.3-0.4 CPU-s and the (k + P)^2 inverse here (166 rim vertices)."""

    def __init__(self, transfer, ids, pull):
        """transfer: the fit's transfer.Transfer; ids (k,) the rim vertices; pull: p."""
        self.transfer, self.pull = transfer, pull
        self.kept = transfer.free[ids]      # a fixed rim vertex stays held: no goal there
        self.rows = (np.cumsum(transfer.free) - 1)[ids[self.kept]]     # in the free unknowns
        self.parts = _floating_parts(transfer, ids[self.kept])
        self.part_means = (sp.diags(1.0 / np.asarray(self.parts.sum(axis=0)).ravel())
                           @ self.parts.T).tocsr()
        # small (k + P, k + P) and well conditioned; its inverse is one product a call
        self.inverse = np.linalg.inv(self._saddle_matrix())

    def _zero_mean(self, values):
        """values (N_free, m) less each floating part's mean."""
        return values - self.parts @ (self.part_means @ values)

    def _saddle_matrix(self):
        k, n_parts = len(self.rows), self.parts.shape[1]
        compliance = np.empty((k, k))
        for chunk in blocks(k, 3 * EXPRESSIONS_PER_BLOCK):      # S A^+ S^T, a few columns at a time
            unit = np.zeros((self.parts.shape[0], chunk.stop - chunk.start))
            unit[self.rows[chunk], np.arange(unit.shape[1])] = 1.0
            balanced = self._zero_mean(self.transfer.solve(self._zero_mean(unit)))
            compliance[:, chunk] = balanced[self.rows]
        translations = self.parts[self.rows].toarray()                         # S T (k, P)
        matrix = np.zeros((k + n_parts, k + n_parts))
        matrix[:k, :k] = (compliance + compliance.T) / 2 + np.identity(k) / self.pull
        matrix[:k, k:] = translations
        matrix[k:, :k] = translations.T
        return matrix

    def __call__(self, offsets):
        """(E, n, 3) the correction that brings the rim vertices by offsets (E, k, 3)."""
        k, e = len(self.rows), len(offsets)
        pulls_and_shifts = self.inverse[:, :k] @ as_columns(offsets[:, self.kept])
        forces = np.zeros((self.parts.shape[0], 3 * e))
        forces[self.rows] = pulls_and_shifts[:k]        # balanced over each floating part
        moved = self.transfer.solve(forces)
        # the translation A^+ leaves out (and rounding's, scaled up by the whisper) made t
        moved -= self.parts @ (self.part_means @ moved - pulls_and_shifts[k:])
        if self.transfer.free.all():
            return as_rows(moved[: self.transfer.n])
        solution = np.zeros((len(self.transfer.free), 3 * e))
        solution[self.transfer.free] = moved
        return as_rows(solution[: self.transfer.n])


def _floating_parts(transfer, ids):
    """Sparse (N_free x P) indicator of the connected parts that hold a rim vertex of `ids` and
    no fixed vertex, over the free unknowns (an augmented formulation's 4th vertices belong to
    their triangle's part): the translations A leaves free."""
    parts = transfer.parts
    if transfer.grad.shape[1] > transfer.n:                     # augmented: the 4th vertices
        parts = np.concatenate([parts, parts[transfer.triangles[:, 0]]])
    floating = np.setdiff1d(np.unique(parts[ids]), np.unique(parts[transfer.fixed]))
    column = np.full(int(parts.max(initial=-1)) + 1, -1)
    column[floating] = np.arange(len(floating))
    of_free = column[parts[transfer.free]]
    rows = np.flatnonzero(of_free >= 0)
    return sp.csr_matrix((np.ones(len(rows)), (rows, of_free[rows])),
                         shape=(len(of_free), len(floating)))
