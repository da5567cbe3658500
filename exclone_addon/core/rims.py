"""Positional goals at the rims of the eye openings (docs/method.md §8, "Rims").

Deformation transfer carries gradients, not positions: a lid whose skin is taller or shorter
than the source's turns by the source's gradients and travels a fraction of the way (the
library's blink left 16% of the demo head's open height, 24-67% of the MakeHuman characters').
Closing an eye is a positional goal.

So after the transfer each eye's lid rows (the visible lid edges the measures read,
core.expression_measures, with the skin beside a coarse rim that lies off the edge as seen: on a
decimated head the straight edges between sparse rim vertices close only if it closes with them)
get a soft target: every rim vertex keeps its transferred motion
towards the viewer, and its motion along the face's up (and along the opening) becomes a goal.
The rest of the face follows by least squares on the transfer's own gradient term:

    min_c  sum_t w_t ||G_t c||^2 + sum_rims p_i / h^2 ||d_i + c_i - g_i||^2

(d the transfer's solution, h the target's mean edge length, p_i the rim vertex's weight). Because
d minimises the gradient term already, d + c is exactly the solution of the transfer with the
positional term added. The goals are linear in the source's deltas (a sum of expressions is
corrected as the sum of its parts) except where the source's lids meet: there the target's rows
are brought together as the measures read them (_GapMatch.closed), so a blink closes whatever
slides along the opening.

The goal comes from the source's own lid rows, station by station (_StationRims): where the
source's row moves up by some share of the source's open height at a station, the rim vertex
moves up by that share of the target's open height at its station (and along the opening by the
source's share of its width), so the eye closes as far as the source's does along the whole lid
however tall either lid is. The up goals are then matched together to the rows' gap at every
station (_GapMatch): on a coarse lid the rows are straight between vertices that stand at
different stations, and vertices that each meet the other row at their own station leave its
bends open between them. The lid's thickness behind its edge (_thickness) takes the edge's goal
at its station where its image lies off the source's own thickness (_unmatched_thickness): the
lid is carried by its edge, not bent at it. Where the target's rows zigzag
(a remeshed face whose rows step between the rim and the skin beyond it, which must not travel
as the rim does) or the source's lids are not found, the goal is the source's motion at the rim
vertex's corresponding point (the vertex map, _MappedRims), unscaled: exact where the
registration is, short where the lids differ in height or the registration misses the inner
corner.
"""
import numpy as np
import scipy.sparse as sp
from scipy.spatial import ConvexHull, QhullError

from . import expression_measures
from .expression_measures import EYE_STATIONS, row_heights, rows_gap
from .transfer import as_columns, as_rows, factorised

# Weight of a rim vertex's goal per unit of squared target edge length (the region's mean). From
# the source's rows: smooth goals, met up to a floating head's common translation (the measured
# gaps within 0.2% of the open height of the goals' own on the low-poly head, 0.1% on the male
# body held at the neck). At 1000 the transfer's gradients held the rims short of them: on the
# 485-vertex low-poly head, whose gap match raises its lower row's bend 0.10 eye widths (30% of
# the open height) where the source's lower lid stays still, by up to 0.014 eye widths (13.3% of
# the open height left at the inner station where the goals leave 9.1%); on the dense heads by
# less (the male body 9.3% for 8.0%); at 100, 19%. From the vertex map: soft enough that a rim
# vertex with a poor image cannot tear the lid.
STATION_WEIGHT = 100000.0
MAPPED_WEIGHT = 100.0
# The target's rows are smooth enough for station goals unless two vertices of a row or more
# stand further than this share of the eye's mean open height inside the row's hull (towards the
# opening): a lid's edge turns one way along the opening, a row that steps between the rim and
# the skin beyond it sinks along a stretch of the rim. The remeshed ICT face of the known-answer
# case: 4 and 2 vertices of its upper rows (0.21-0.49); every shared character and its variants
# (units, mirrored, triangulated, subdivided, decimated), the demo head and ICT: none (at most
# 0.14). One vertex is a coarse lid's own bend: the 485-vertex low-poly head's lower rows (four
# vertices each) rise 0.38 at the outer corner onto the back of the lid's thickness, seen from the
# front there, which the closing upper row meets. A fit (a cubic through the row) misread coarse
# rows: a decimated head's row ending on an eye corner stood 0.199 from a parabola.
ROUGH = 0.2
# The rows' gap is matched at this many stations between their common ends, and each rim vertex
# kept near its own station goal with this weight against the gap's mean square.
GAP_STATIONS = 50
GAP_GOALS = 0.01
# Rounds of closing an eye whose source's lids meet, its rows read as the measures read them
# (_GapMatch.closed): 4 and 8 the same to 0.001 of the open height.
MEETING_ROUNDS = 4
# A source's eye closes where its lids meet at a measured station and stand on average over
# them no further apart than this share of their open height: the library's blinks -0.03 / -0.02
# (they cross in the middle, 8-10% open at the inner corner), its eyeLookDown 0.35 (no station
# meets). Lids that touch at one station of a lid left open elsewhere are not a closing eye.
CLOSING = 0.2
# A lid's thickness behind its edge (the rows' vertices carried with the edge) lies no further
# behind it than this x the open height at its station: ICT's lids within 0.46 (their edge
# alone held, the thickness behind the outer half, which the transfer closed where the edge
# stayed half open, went on down with the edge's correction: 0.58 of the open height below the
# lower lid, a notch); the MakeHuman heads' lids within 1 and their sockets' walls 2.2-7 behind.
THICKNESS = 1.0
# ... and where the lids stand at least this share of their mean open height apart: towards the
# corners the rows meet and what lies between them is the corner's skin, which the carried
# thickness pinched (the library's blink onto the MakeHuman child: a triangle turned over at the
# outer corner, excess stretch 1.54 -> 2.29; with this 1.50, the ICT neutral's lid as without it).
OPEN = 0.5


class RimGoals:
    """The eyes' rim rows on the welded target region, and the factorised correction."""

    def __init__(self, region, source_vertices, source_triangles, source_landmark_ids,
                 landmark_names, landmark_ids, vertex_map, transfer):
        """region: surface.Surface of the target triangles the transfer solves (welded numbering);
        source_vertices (n_source, 3): the aligned source (the target's frame, welded numbering);
        source_triangles: the source region's triangles; source_landmark_ids, landmark_names,
        landmark_ids: the fit's source and target landmarks (welded ids); vertex_map: the fit's
        correspondence.VertexMap; transfer: the fit's transfer.Transfer (its gradient operator
        and weights)."""
        names = [str(name) for name in landmark_names]
        openings = expression_measures.Openings(
            region.vertices, region.triangles, dict(zip(names, np.asarray(landmark_ids).tolist())))
        source_openings = expression_measures.Openings(
            source_vertices, source_triangles,
            dict(zip(names, np.asarray(source_landmark_ids).tolist()))) if openings.lids else None
        self.openings = openings
        self.eyes = []
        for key, lids in openings.lids.items():
            source_lids = source_openings.lids.get(key)
            # both eyes' rows must trace a lid: a source whose lashes join its lids (an
            # unwelded ICT welded by position) shows rows of two vertices on the lashes
            eye = _StationRims(lids, source_lids, region.vertices, source_vertices) \
                if source_lids is not None and _smooth(lids, region.vertices) \
                and _smooth(source_lids, source_vertices) \
                else _MappedRims(lids, vertex_map, source_triangles)
            if eye.usable:
                # the station goals' lid carries its thickness where it maps off the source's:
                # held by its edge alone, it keeps the transfer's motion plus the edge's correction
                eye.thickness, eye.carried = _unmatched_thickness(
                    lids, source_lids, region.vertices, openings.used, source_vertices,
                    source_openings.used, source_triangles, vertex_map) \
                    if isinstance(eye, _StationRims) \
                    else (np.zeros(0, dtype=np.int64), np.zeros((0, len(eye.ids))))
                self.eyes.append(eye)
        self.ids = np.concatenate([np.concatenate([eye.ids, eye.thickness])
                                   for eye in self.eyes]) if self.eyes \
            else np.zeros(0, dtype=np.int64)
        pulls = np.concatenate([np.full(len(eye.ids) + len(eye.thickness), eye.weight)
                                for eye in self.eyes]) \
            / region.mean_edge_length ** 2 if self.eyes else np.zeros(0)
        self.solve = _Correction(transfer, self.ids, pulls, np.flatnonzero(vertex_map.valid)) \
            if len(self.ids) else None

    def __call__(self, result, source_deltas):
        """The transferred displacements `result` (E, n, 3) with the rims brought to their goals;
        source_deltas (E, n_source, 3): the expressions on the aligned source."""
        if self.solve is None:
            return result
        goals = []
        for eye in self.eyes:
            moved = result[:, eye.ids]
            # the solved motion kept but along the eye's axes (orthonormal): there, the goal's
            rim = moved + (eye.motion(source_deltas) - moved @ eye.axes.T) @ eye.axes
            goals += [rim, np.einsum("tk,ekc->etc", eye.carried, rim)]
        goals = np.concatenate(goals, axis=1)                                   # (E, k, 3)
        return result + self.solve(goals - result[:, self.ids])


def _unmatched_thickness(lids, source_lids, vertices, used, source_vertices, source_used,
                         source_triangles, vertex_map):
    """_thickness of the target's lids, less the vertices whose image lies on the source's own
    lid thickness (the vertex map's nearest corner is one of the source's _thickness): those
    move as the source's thickness does (a target of the source's own base mesh, vertex by
    vertex: exactly). Carried with the edge are the others, whose image the registration put on
    the skin over the source's lid or on none. used, source_used: the surfaces' vertices (the
    Openings')."""
    ids, carried = _thickness(lids, vertices, used)
    source_thickness, _ = _thickness(source_lids, source_vertices, source_used)
    corners = source_triangles[vertex_map.triangle[ids]]
    nearest = corners[np.arange(len(ids)), np.argmax(vertex_map.bary[ids], axis=1)]
    unmatched = ~(vertex_map.valid[ids] & np.isin(nearest, source_thickness))
    return ids[unmatched], carried[unmatched]


def _thickness(lids, vertices, used):
    """(ids, (t, k) weights over the rim rows' vertices, upper then lower) the lids' thickness
    behind their edges: the surface's vertices (`used`) between a row and the opening's middle
    at rest, within the row's stations where the lids stand OPEN x their mean open height apart
    or more, behind the row by no more than THICKNESS x the open height there. Each is carried
    with its row: its goal the row's goal at its station (linear between the row's vertices)."""
    opening = lids.opening
    s, h, z = opening.station(vertices[used]), opening.height(vertices[used]), \
        opening.depth(vertices[used])
    upper, lower = lids.upper_margin, lids.lower_margin
    top = row_heights(opening, vertices[upper], s)
    bottom = row_heights(opening, vertices[lower], s)
    middle, gap = (top + bottom) / 2, top - bottom
    ids, carried = [], []
    rows = np.concatenate([upper, lower])
    at = [np.arange(len(upper)), len(upper) + np.arange(len(lower))]
    for row, sign, edge, columns in ((upper, 1, top, at[0]), (lower, -1, bottom, at[1])):
        stations = opening.station(vertices[row])
        # the depth test last, on the few vertices beside the row: its weights are (vertices,
        # row) and all of the surface's would be most of the rims' set-up
        near = np.flatnonzero(
            (s > stations.min()) & (s < stations.max()) & (gap > OPEN * lids.rest.mean())
            & (sign * (h - middle) > 0) & (sign * (edge - h) > 0) & ~np.isin(used, rows))
        along_row = _interpolation(stations, s[near])
        depth = along_row @ opening.depth(vertices[row])
        inside = (z[near] < depth) & (z[near] > depth - THICKNESS * gap[near])
        weights = np.zeros((inside.sum(), len(rows)))
        weights[:, columns] = along_row[inside]
        ids.append(used[near[inside]])
        carried.append(weights)
    return np.concatenate(ids), np.concatenate(carried)


def _smooth(lids, vertices):
    """Whether each of the eye's rows (of three vertices or more: a coarse lid's rim can be
    three) has fewer than two vertices standing more than ROUGH x its mean open height inside its
    hull on the far side from the opening (heights along the stations)."""
    for row, sign in ((lids.upper, 1), (lids.lower, -1)):
        if len(row) < 3:
            return False
        stations = lids.opening.station(vertices[row])
        heights = sign * lids.opening.height(vertices[row])
        if np.count_nonzero(_dents(stations, heights) > ROUGH * lids.rest.mean()) >= 2:
            return False
    return True


def _dents(stations, heights):
    """How far each of a row's vertices (stations, heights) stands below the row's upper hull:
    0 all along a row that turns one way (an arch), the depth of each notch otherwise."""
    try:
        facets = ConvexHull(np.column_stack([stations, heights])).equations  # a s + b h + c <= 0
    except QhullError:                  # all on one line: no notch
        return np.zeros(len(stations))
    upper = facets[facets[:, 1] > 0]
    # a concave hull is the lowest of its facets' lines
    hull = np.min(-(upper[:, :1] * stations + upper[:, 2:]) / upper[:, 1:2], axis=0)
    return hull - heights


class _StationRims:
    """One eye's rim rows with goals from the source's own lid rows, station by station: at a
    rim vertex's station along the opening, the source's row moves up by some share of the
    source's open height there; the rim vertex moves up by that share of the target's open height
    at the same station, and along the opening by the source's row's motion along it as a share
    of the source's width, times the target's (the inner corner's rim, where the lid's height
    changes fastest, reads a slide along as an opening); the motions up matched together to the
    source's gap's change at every station (_GapMatch). The eye closes (opens) as far as
    the source's does, along the whole lid, however tall the two lids are, linear in the source's
    deltas; where the source's lids meet, the target's meet along the whole lid."""

    weight = STATION_WEIGHT

    def __init__(self, lids, source_lids, vertices, source_vertices):
        """lids, source_lids: expression_measures' lids of the eye on the rest target and the rest
        (aligned) source (their margin rows pulled); vertices, source_vertices: the rest positions
        they are on."""
        self.axes = np.stack([lids.opening.up, lids.opening.along])
        self.source_axes = np.stack([source_lids.opening.up, source_lids.opening.along])
        upper, lower = lids.upper_margin, lids.lower_margin
        source_upper, source_lower = source_lids.upper_margin, source_lids.lower_margin
        self.ids = np.concatenate([upper, lower])
        self.source_ids = np.concatenate([source_upper, source_lower])
        stations = lids.opening.station(vertices[self.ids])
        height_scale = _height_ratio(lids, source_lids, vertices, source_vertices, stations)
        share = np.zeros((len(self.ids), len(self.source_ids)))
        at = [slice(0, len(upper)), slice(len(upper), len(self.ids))]
        of = [slice(0, len(source_upper)), slice(len(source_upper), len(self.source_ids))]
        for mine, theirs in zip(at, of):
            share[mine, theirs] = _interpolation(
                source_lids.opening.station(source_vertices[self.source_ids[theirs]]),
                stations[mine])
        self.gaps = _GapMatch(lids, source_lids, vertices, source_vertices, upper, lower,
                              source_upper, source_lower, height_scale[:, None] * share)
        # (axis, k, source rim vertices): up by the heights' ratio, along by the widths'
        self.shares = np.stack([self.gaps.up,
                                share * lids.opening.width / source_lids.opening.width])
        self.usable = min(len(upper), len(lower)) >= 2

    def motion(self, source_deltas):
        """(E, k, 2) each rim vertex's goal motion along the face's up and the opening."""
        along_axes = source_deltas[:, self.source_ids] @ self.source_axes.T      # (E, m, 2)
        goals = np.stack([along_axes[..., a] @ self.shares[a].T for a in range(2)], axis=-1)
        return self.gaps.closed(goals, source_deltas[:, self.source_ids], along_axes[..., 0])


def _gap_operator(opening, vertices, upper, lower, stations):
    """(S, len(upper) + len(lower)) the gap between the rows (linear between their vertices) at
    the stations, as weights on the rows' vertices' heights: upper minus lower."""
    return np.hstack([_interpolation(opening.station(vertices[upper]), stations),
                      -_interpolation(opening.station(vertices[lower]), stations)])


class _GapMatch:
    """The rim vertices' goal motions up matched to the source's gap: the rows' gap at every
    station between the rows' common ends changes by the source's gap's change there as a share
    of the source's open height, times the target's; each vertex as near its own station goal as
    that allows (GAP_GOALS). On a coarse lid the rows' vertices stand at different stations and
    each row is straight between its own: vertices that each meet the other row at their own
    station still leave the other row's bends open between them. `up` (k, source rim vertices):
    those motions as weights on the source rim vertices' motions up (the rows moving up only);
    `closed` brings a closing eye's rows together as the measures read them."""

    def __init__(self, lids, source_lids, vertices, source_vertices, upper, lower, source_upper,
                 source_lower, own):
        """lids, source_lids, vertices, source_vertices as _StationRims'; upper, lower,
        source_upper, source_lower: the margin rows; own (k, source rim vertices): each rim
        vertex's station goal, as weights on the source rim vertices' motions up."""
        self.opening, self.source_opening = lids.opening, source_lids.opening
        self.rows = (np.arange(len(upper)), len(upper) + np.arange(len(lower)))
        self.source_rows = (np.arange(len(source_upper)),
                            len(source_upper) + np.arange(len(source_lower)))
        self.rest = vertices[np.concatenate([upper, lower])]
        self.source_rest = source_vertices[np.concatenate([source_upper, source_lower])]
        self.axes = np.stack([lids.opening.up, lids.opening.along])
        ends = [max(self.opening.station(vertices[row]).min() for row in (upper, lower)),
                min(self.opening.station(vertices[row]).max() for row in (upper, lower))]
        self.stations = np.linspace(*ends, GAP_STATIONS)
        self.ratio = _height_ratio(lids, source_lids, vertices, source_vertices, self.stations)
        self.rest_gap = self._gaps(self.opening, self.rest[None], self.rows)[0]
        self.source_rest_gap = self._gaps(self.source_opening, self.source_rest[None],
                                          self.source_rows)[0]
        # a vertex on both rows (where the lids meet) is one unknown, its own goal the rows' mean
        vertex_ids, of_row = np.unique(np.concatenate([upper, lower]), return_inverse=True)
        self.each = np.zeros((len(of_row), len(vertex_ids)))
        self.each[np.arange(len(of_row)), of_row] = 1.0
        self.mean = self.each / self.each.sum(axis=0)
        self.own = self.mean.T @ own
        gap = _gap_operator(self.opening, vertices, upper, lower, self.stations) @ self.each
        wanted = self.ratio[:, None] * _gap_operator(self.source_opening, source_vertices,
                                                     source_upper, source_lower, self.stations)
        normal = gap.T @ gap / GAP_STATIONS + GAP_GOALS * np.identity(len(vertex_ids))
        self.up = self.each @ np.linalg.solve(normal, gap.T @ wanted / GAP_STATIONS
                                              + GAP_GOALS * self.own)

    def closed(self, goals, source_moves, source_up):
        """goals (E, k, 2) (up, along), where the source's eye closes (its rows' gap, read as the
        measures read it, at or below nought at a measured station and on average over them
        within CLOSING of the open height) with the motions up refitted
        (Gauss-Newton) so that the target's rows meet too, read alike, wherever the source's
        leave a gap: where they cross, the target's cross by the source's share. The rest
        unchanged. source_moves (E, m, 3): the source rim vertices' motions, source_up their
        motions up.

        Read at the rest stations, a row that slides along the opening reads lid that stood
        elsewhere: at the inner corner, where the open height changes fastest, the ICT library's
        blink slides its lid towards the nose and leaves 8-10% of the open height there where
        its rows' motions up alone leave 16%, and the linear weights, which see the motions up
        alone, closed a new ICT identity's lids to 10-12%; refitted to the source's own reading
        instead, the MakeHuman characters' stayed 9.7-12% open (a coarse row cannot follow the
        source's closure at every station). A closing eye closes."""
        source_gaps = self._gaps(self.source_opening, self.source_rest + source_moves,
                                 self.source_rows)
        measured = (self.stations >= EYE_STATIONS[0]) & (self.stations <= EYE_STATIONS[-1])
        shares = source_gaps[:, measured] / self.source_rest_gap[measured]
        closing = np.flatnonzero((shares.min(axis=1, initial=np.inf) <= 0.0)
                                 & (shares.mean(axis=1) <= CLOSING))
        wanted = np.minimum(self.ratio * (source_gaps[closing] - self.source_rest_gap)
                            + self.rest_gap, 0.0)
        own = source_up[closing] @ self.own.T                                  # (C, unique)
        goals = goals.copy()
        for e, meeting, near in zip(closing, wanted, own):
            up = goals[e, :, 0] @ self.mean
            for _ in range(MEETING_ROUNDS):
                moved = self.rest + goals[e] @ self.axes
                # the gap at the stations, linear in the rows' heights where they now stand
                reading = _gap_operator(self.opening, moved, *self.rows, self.stations)
                gap = reading @ self.each
                missing = meeting - reading @ self.opening.height(moved)
                normal = gap.T @ gap / GAP_STATIONS + GAP_GOALS * np.identity(len(up))
                up = up + np.linalg.solve(normal, gap.T @ missing / GAP_STATIONS
                                          + GAP_GOALS * (near - up))
                goals[e, :, 0] = self.each @ up
        return goals

    def _gaps(self, opening, rows, which):
        """(E, S) the upper row's height over the lower row's at the stations; rows (E, k, 3)."""
        upper, lower = which
        return np.stack([rows_gap(opening, points[upper], points[lower], self.stations)
                         for points in rows])


def _height_ratio(lids, source_lids, vertices, source_vertices, stations):
    """(S,) the target's open height over the source's at the stations; beyond the outermost
    stations measured (EYE_STATIONS) the ratio there: the heights vanish at the corners."""
    measured = np.clip(stations, EYE_STATIONS[0], EYE_STATIONS[-1])
    return _open_height(lids, vertices, measured) \
        / _open_height(source_lids, source_vertices, measured)


def _open_height(lids, vertices, stations):
    """(S,) the eye's rest gap between its margin rows at the stations."""
    return rows_gap(lids.opening, vertices[lids.upper_margin], vertices[lids.lower_margin],
                    stations)


def _interpolation(known, wanted):
    """(len(wanted), len(known)) weights of linear interpolation along one axis (known stations
    to wanted ones, the nearest end's value beyond them), as np.interp."""
    order = np.argsort(known)
    weights = np.zeros((len(wanted), len(known)))
    weights[:, order] = np.stack([np.interp(wanted, known[order], unit)
                                  for unit in np.identity(len(known))], axis=1)
    return weights


class _MappedRims:
    """One eye's rim rows where the source's lids are not found: each rim vertex's goal motion
    along the face's up is the source's at its corresponding point (the vertex map)."""

    weight = MAPPED_WEIGHT

    def __init__(self, lids, vertex_map, source_triangles):
        """lids: expression_measures' lids of the eye on the rest target; vertex_map: the fit's
        correspondence.VertexMap; source_triangles: the source region's triangles."""
        self.axes = lids.opening.up[None]
        mapped = vertex_map.valid
        rows = (lids.upper_margin, lids.lower_margin)
        self.ids = np.concatenate([row[mapped[row]] for row in rows])
        self.usable = min(mapped[row].sum() for row in rows) >= 2
        self.vertex_map, self.source_triangles = vertex_map, source_triangles

    def motion(self, source_deltas):
        """(E, k, 1) the source's motion along the face's up at the rim vertices' images."""
        moves = self.vertex_map.sample(np.moveaxis(source_deltas, 0, 1), self.source_triangles,
                                       self.ids)                               # (k, E, 3)
        return np.moveaxis(moves @ self.axes.T, 0, 1)


class _Correction:
    """The correction c of the module docstring: with A = G^T W G (the transfer's normal matrix,
    its whisper of regularisation included), P the rim vertices' pulls (diagonal), S their rows
    and r their offsets, c solves (A + S^T P S) c = S^T P r, factorised once per fit; each block
    of expressions then costs one back-substitution. The goals set the shape, not where a
    floating part sits: its translation is then set as the transfer sets it (no mean motion at
    its anchors), else rim goals that differ from the solved motion by a common amount carried
    the whole face along (the remeshed known case's blink: 350% error).

    Woodbury's identity on the transfer's own factorisation gives the same c (to 3e-8 of the
    largest motion) with one back-substitution column per pulled vertex, so its cost grows with
    the target's density squared: a dense lid's rows and the thickness behind them are hundreds
    (748 on a 50k-vertex head: its transfer 4.4-5.2 s with them, 3.8-4.5 s with this
    factorisation, which holds 75-90 MiB more at its peak; at 100k 12.2 s against 9.2 s)."""

    def __init__(self, transfer, ids, pull, anchors):
        """transfer: the fit's transfer.Transfer; ids (k,) the rim vertices; pull (k,): P; anchors:
        the vertices that set each floating part's translation in the transfer (the mapped ones)."""
        self.transfer, self.anchors = transfer, anchors
        self.kept = transfer.free[ids]      # a fixed rim vertex stays held: no goal there
        self.ids, self.pull = ids[self.kept], pull[self.kept]
        rows = (np.cumsum(transfer.free) - 1)[self.ids]                    # in the free unknowns
        size = int(transfer.free.sum())
        # a vertex on both rows (where the lids meet) takes both pulls
        pins = sp.csc_matrix((self.pull, (rows, rows)), shape=(size, size))
        _, self.solve = factorised(transfer.normal_matrix + pins)

    def __call__(self, offsets):
        """(E, n, 3) the correction that brings the rim vertices by offsets (E, k, 3), each
        floating part's translation set as the transfer sets it (no mean motion at its anchors)."""
        e = len(offsets)
        forces = np.zeros((len(self.transfer.free), 3 * e))
        np.add.at(forces, self.ids, self.pull[:, None] * as_columns(offsets[:, self.kept]))
        return as_rows(self.transfer.solved(forces, np.zeros((len(self.anchors), 3 * e)),
                                            self.anchors, solve=self.solve))
