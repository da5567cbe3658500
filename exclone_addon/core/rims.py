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
from .transfer import factorised

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
        self.solve = _correction_solver(transfer, self.ids, region) if len(self.ids) else None

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


def _correction_solver(transfer, ids, region):
    """solve(offsets (E, k, 3)) -> (E, n, 3): the correction c of the module docstring that
    brings the rim vertices `ids` by `offsets` (softly) and keeps the transfer's gradients."""
    grad = transfer.grad
    weights = sp.diags(np.repeat(transfer.row_weight, 3))
    normal = (grad.T @ weights @ grad).tocsc()
    pull = RIM_WEIGHT / region.mean_edge_length ** 2
    pin = np.zeros(normal.shape[0])
    pin[ids] = pull
    # the transfer's held vertices (if any) stay held; the rest as in transfer.Transfer
    free = np.asarray(getattr(transfer, "free", np.ones(normal.shape[0], dtype=bool)))
    system = (normal + sp.diags(pin))[free][:, free]
    eps = 1e-10 * system.diagonal().mean()
    _, solve = factorised((system + eps * sp.identity(system.shape[0])).tocsc())
    n = len(region.vertices)

    def correction(offsets):
        e = len(offsets)
        rhs = np.zeros((normal.shape[0], e, 3))
        rhs[ids] = pull * np.moveaxis(offsets, 0, 1)
        solution = np.zeros_like(rhs)
        solution[free] = solve(rhs[free].reshape(int(free.sum()), -1)).reshape(-1, e, 3)
        return np.moveaxis(solution[:n], 1, 0)
    return correction
