"""Positional goals at the rims of the eye openings (docs/method.md §8, "Rims").

Deformation transfer carries gradients, not positions: a lid whose skin is taller or shorter
than the source's, or whose rim maps a little off the source's rim, turns by the source's
gradients and travels a fraction of the way (the library's blink left 16% of the demo head's
open height). Closing an eye is a positional goal: the gap between the lids at each station
along the opening must become the share of its rest height that the source's gap becomes.

So after the transfer, each eye's lid rows (the visible lid edges the measures read,
core.expression_measures) get a soft target: every rim vertex keeps its transferred motion
across and along the face, and its motion along the face's up becomes the source's at its
corresponding point (the vertex map) scaled by the ratio of the two faces' rest gaps at that
station. That scale makes a source gap of f x its rest height a target gap of f x the target's.
The rest of the face follows by least squares on the transfer's own gradient term:

    min_c  sum_t w_t ||G_t c||^2 + RIM_WEIGHT / h^2 sum_rims ||d_i + c_i - g_i||^2

(d the transfer's solution, h the target's mean edge length). Because d minimises the gradient
term already, d + c is exactly the solution of the transfer with the positional term added.
The goals are linear in the source's deltas, so a sum of expressions (jawOpen + mouthClose) is
corrected as the sum of its parts.
"""
import numpy as np
import scipy.sparse as sp

from . import expression_measures
from .transfer import factorised

# Weight of a rim vertex's goal per unit of squared target edge length: strong enough that the
# rims reach their goals within a few percent of the lid's travel, soft enough that a rim vertex
# with a poor image cannot tear the lid.
RIM_WEIGHT = 100.0
# The two faces' rest-gap ratio is trusted within these bounds (images that collapse onto one
# lid would make it absurd).
SCALE_RANGE = (1 / 3, 3.0)


class RimGoals:
    """The eyes' rim rows on the welded target region, and the factorised correction."""

    def __init__(self, region, source_vertices, source_triangles, landmark_names, landmark_ids,
                 vertex_map, transfer):
        """region: surface.Surface of the target triangles the transfer solves (welded numbering);
        source_vertices/triangles: the source aligned to the target (welded) and its region's
        triangles; landmark_names/ids: the fit's target landmarks (welded ids); vertex_map: the
        fit's correspondence.VertexMap; transfer: the fit's transfer.Transfer (its gradient
        operator and weights)."""
        openings = expression_measures.Openings(
            region.vertices, region.triangles,
            {str(name): int(i) for name, i in zip(landmark_names, landmark_ids)})
        self.eyes = [eye for eye in (_EyeRims(lids, region.vertices, vertex_map.valid)
                                     for lids in openings.lids.values()) if eye.usable]
        self.ids = np.concatenate([eye.ids for eye in self.eyes]) if self.eyes \
            else np.zeros(0, dtype=np.int64)
        self.images = _Images(vertex_map, source_triangles, self.ids)
        self.rest_at = self.images.at(source_vertices[None])[0]
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
            goals.append(eye.goals(result, self.rest_at[mine], moves_at[:, mine]))
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
    """One eye's mapped rim vertices: the upper row, then the lower row, with their stations
    along the opening and the target's rest gap there."""

    def __init__(self, lids, vertices, mapped):
        """lids: expression_measures' lids of the eye on the rest target (vertices)."""
        self.opening = lids.opening
        rows = [row[mapped[row]] for row in (lids.upper, lids.lower)]
        self.usable = min(len(row) for row in rows) >= 2
        self.ids = np.concatenate(rows)
        self.upper = np.arange(len(self.ids)) < len(rows[0])
        self.stations = self.opening.station(vertices[self.ids])
        self.target_rest = self._gap(vertices[self.ids])

    def _row_height(self, positions, row):
        """(k,) the height of `row`'s points (positions of all rim vertices) at every rim
        vertex's station (linear between the row's own stations)."""
        order = np.argsort(self.stations[row])
        return np.interp(self.stations, self.stations[row][order],
                         self.opening.height(positions[row])[order])

    def _gap(self, positions):
        """(k,) the upper row's height above the lower row's at every rim vertex's station."""
        return self._row_height(positions, self.upper) - self._row_height(positions, ~self.upper)

    def goals(self, result, images_rest, images_moves):
        """(E, k, 3): each rim vertex's transferred motion with its motion along the face's up
        replaced by its image's on the source (images_rest (k, 3), images_moves (E, k, 3): the
        aligned source at the rim vertices' images), scaled by the faces' mean open heights."""
        # one scale per eye, the ratio of the two faces' mean open heights: per station the
        # ratio carries the images' small slips along the lid (on the same face remeshed it
        # varied by 6% around 1 and cost 6% of the blink's error)
        source_rest = self._gap(images_rest).sum()
        scale = self.target_rest.sum() / source_rest if source_rest > 0 else 1.0
        scale = float(np.clip(scale, *SCALE_RANGE))
        up = self.opening.up
        moved = result[:, self.ids]
        wanted = scale * (images_moves @ up)                                    # (E, k)
        return moved + (wanted - moved @ up)[..., None] * up


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
