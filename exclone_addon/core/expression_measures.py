"""Measures of cloned expressions on the target: do they read right on this face?
(docs/method.md §13).

Per expression: how far each eye's lids still stand apart (a fraction of their open height at
rest, at EYE_STATIONS along the whole lid) and how far the upper lid passes below the lower lid's
edge (its thickness or skin dragged through it, a notch), how much further apart the lips stand
than at rest (a fraction of the face's diagonal), the worst edge stretch, the triangles turned
over, and how far anything outside the solved region moved.

An eye's lids are found on the rest target from its corner landmarks and its surface, as a
person finds them: seen from the front (a headlight render along the face's forward,
core.face_render). In each pixel column between the corners, going up (down) from the corners'
line, the lid's edge is where the first steep stretch ends: the opening (no surface, or the
socket far behind) and the surface turned more than 45 degrees away (a fold into the socket, the
top of a lid modelled with a thickness) give way to the lid's front. The vertex nearest that
point joins the lid's row, and each row keeps the vertices nearest the opening (not a crease
above it). However the eye is modelled (a hole, a socket, thick lids, a coarse game mesh) this
is the edge one sees. Where there is none the measure is None with the reason. The lids are
followed by vertex id through every expression, so a lid that slides down reads as its vertices
do. The lips are the upper and
lower lip landmarks, which move with the lips however the mouth is modelled.
"""
import numpy as np
from scipy import ndimage

from . import mesh
from .deformation import triangle_adjacency
from .face_render import Camera, render
from .proximity import interpolate
from .surface import Surface

# Stations along the eye opening from the inner to the outer corner, as fractions of the
# corners' distance: the whole lid, not only its middle; the corners themselves are left out
# (the gap closes there on any face).
EYE_STATIONS = np.linspace(0.2, 0.8, 7)
# The eye is seen from the front in a VIEW_PIXELS square image VIEW_WIDTH x its width across.
VIEW_PIXELS = 240
VIEW_WIDTH = 1.4
# Where the surface, seen from the front, turns away by more than 45 degrees (depth change per
# unit of height), the lid's edge is near: the opening behind it, or the fold into a socket.
STEEP = 1.0
# The opening behind the lids lies at least this far (x the eye's width) behind their edge.
OPEN_DEPTH = 0.1
# The eye's view draws the surface down to this far (x the eye's width) behind the corners.
VIEW_DEPTH = 2.0
# A lid's edge lies at most this far (x the eye's width) behind the corners' line; a socket's
# walls seen through the opening lie further back (ICT's outer socket: 0.8 behind).
LID_DEPTH = 0.4
# A lid's edge lies within this height (x the eye's width) above where its surface begins: the
# demo head's lower lid shows its thickness over 0.05-0.1 of it; the remeshed ICT face's upper
# lid is one steep facet up to its crease, 0.3 above.
NEAR_EDGE = 0.1
# A lid's visible edge is the one nearest the opening among its margin candidates within this
# many stations.
EDGE_WINDOW = 0.05
# A margin vertex standing further than this (x the eye's width) beyond the straight line between
# its row's neighbours, away from the opening, is skin above (below) the lid's edge, not the edge:
# a coarse mesh's edge triangle may have its nearest corner there, with its rim vertices further
# apart than EDGE_WINDOW (the shared man, old woman and stylised head through Decimate collapse
# 0.5: 0.099-0.187). The shared characters' and the demo head's rows, whose lids arch between
# their vertices, keep within 0.034.
STANDS_OFF = 0.09
# A margin vertex standing further than this (x the eye's width) beyond the lid's edge as seen from
# the front (away from the opening, at its station) is skin beside the rim: on a coarse mesh the
# edge between two sparse rim vertices is one straight mesh edge and the skin vertex of an edge
# triangle lies off it, where its row's neighbours' line (STANDS_OFF) may not tell it from the
# lid's arch (the shared man and old woman through Decimate collapse 0.5: 0.057-0.081). The
# measures read the rows without it; the rims pull it with the rim (core.rims). Every undecimated
# shared character and variant keeps within 0.021, the demo head and the library within 0.002.
OFF_EDGE = 0.04
# The corner landmarks miss the eye's opening where both lids' edges are seen from their line in
# fewer than this share of the measured stations' columns: the 485-vertex low-poly head's
# automatic corners stand on its lids and skin, 0.16-0.45 eye widths off the opening's ends (its
# right eye's line runs along the upper lid, the lower one out of reach beyond half the opening:
# 0.43); every shared character, variant, the demo head and the library 0.80-1.0, the remeshed
# known case and its ICT source 0.74-0.92. Then, or where the landmarks' lids read closed at rest,
# the corners are the ends of the opening seen from the front (_opening_ends).
THROUGH = 0.5
# Where no opening is seen in the eye's view, it is looked for in a view this many times the
# corners' distance across (and where the opening runs out of the view, in one that wide around
# the part seen); the ends are looked for in at most LOOKS views, each centred on the last one's
# ends, until the whole opening is in the eye's view.
WIDE_VIEW = 6.0
LOOKS = 5
# The lids are looked for within this far of the corners' line, x the corners' distance.
EYE_REACH = 0.35
# An edge's image on the source shorter than this share of the edge has collapsed (both ends on
# one point of the source): its stretch ratio means nothing.
COLLAPSED = 1e-3

EYES = ("left", "right")
COMBINED = ("jawOpen", "mouthClose")      # measured together: the lips should meet again
MEASURED_TOGETHER = "+".join(COMBINED)


class FaceAxes:
    """The face's axes from its landmarks: up (eyes above the lips), forward (to the nose tip),
    each a unit vector in the mesh's coordinates."""

    def __init__(self, points):
        eyes = np.mean([points[f"eye_{end}_{side}"] for end in ("inner", "outer") for side in EYES],
                       axis=0)
        lips = (points["upper_lip"] + points["lower_lip"]) / 2
        across = points["eye_outer_left"] - points["eye_outer_right"]
        across = across / np.linalg.norm(across)
        up = eyes - lips
        up = up - (up @ across) * across
        self.up = up / np.linalg.norm(up)
        forward = np.cross(across, self.up)
        self.forward = forward if forward @ (points["nose_tip"] - eyes) >= 0 else -forward


class _Opening:
    """Two corners of an opening (an eye) in the face frame: a point's station s (0 at the
    first corner, 1 at the second, along the face's across axis), its height h above the
    corners' line (along the face's up) and its depth in front of it (along the face's
    forward); moving a point up or down changes only its height."""

    def __init__(self, first, second, frame):
        self.first, self.forward, self.up = first, frame.forward, frame.up
        along = second - first
        self.rise, self.sink = float(along @ frame.up), float(along @ frame.forward)
        along = along - (along @ frame.forward) * frame.forward - self.rise * frame.up
        self.width = float(np.linalg.norm(along))
        self.along = along / self.width

    def station(self, points):
        return (points - self.first) @ self.along / self.width

    def height(self, points):
        return (points - self.first) @ self.up - self.station(points) * self.rise

    def depth(self, points):
        """How far in front of the corners' line (along the face's forward)."""
        return (points - self.first) @ self.forward - self.station(points) * self.sink


def _eye_view(vertices, triangles, opening, width=VIEW_WIDTH):
    """The eye seen from the front (face_render, orthographic along the face's forward), `width`
    x its width across:
    ((P * P, 3) each pixel's ray origin, row by row, (P, P) depth of each pixel along forward
    (-inf where no surface), (P, P, 3) the surface point seen, (P, P) its triangle (-1 for
    none)). Only the triangles within VIEW_DEPTH
    eye widths behind the corners are drawn: what lies further back (the back of the head seen
    through a hole) reads as the opening all the same, and costs most of the drawing."""
    centre = opening.first + 0.5 * opening.width * opening.along + 0.5 * opening.rise * opening.up
    camera = Camera.looking(centre, opening.forward, opening.up, width * opening.width,
                            VIEW_PIXELS)
    near = (vertices - centre) @ opening.forward > -VIEW_DEPTH * opening.width
    # nor those wholly beyond one side of the image (a pixel's margin): they cover no pixel
    # centre, but their projection and pixel boxes were most of a dense head's drawing
    half = 0.5 * width * opening.width + camera.pixel_size
    across = [(vertices - centre) @ axis / half for axis in camera.axes[:2]]     # right, up
    outside = np.any([np.all(ends > 1, axis=1) | np.all(ends < -1, axis=1)
                      for ends in (side[triangles] for side in across)], axis=0)
    drawn = np.flatnonzero(near[triangles].any(axis=1) & ~outside)
    seen = render(vertices, triangles[drawn], camera, shaded=False)     # what is seen, not how
    pixels = np.stack(np.meshgrid(np.arange(VIEW_PIXELS), np.arange(VIEW_PIXELS)), axis=-1)
    points, triangle = seen.surface_points(pixels.reshape(-1, 2))
    triangle[triangle >= 0] = drawn[triangle[triangle >= 0]]
    depth = np.where(triangle >= 0, (points - centre) @ opening.forward, -np.inf)
    shape = (VIEW_PIXELS, VIEW_PIXELS)
    return (camera.ray_origins(pixels.reshape(-1, 2)), depth.reshape(shape),
            points.reshape(shape + (3,)), triangle.reshape(shape))


def _edge_pixels(depth, heights, width, length):
    """Per column of (L, C) pixels ordered from the corners' line outwards (`length` (C,) of
    them each; the rest padding), at `heights`, the index of the lid's edge: where the first
    steep stretch (the surface turned more than 45 degrees away from the viewer, or no surface:
    the opening, a fold into a socket, the top of a lid's thickness) ends, but no more than
    NEAR_EDGE x the eye's width (`width`) above where the lid's surface begins (after the
    opening, or a jump in depth from a socket behind): a coarse mesh's lid may be one steep facet
    up to its crease. -1 where the column has none. All columns at once: one at a time, the
    calls were most of the lids' cost."""
    with np.errstate(invalid="ignore"):         # no surface is depth -inf: its steps are NaN
        step = np.diff(depth, axis=0)
        slope = step / np.maximum(np.abs(np.diff(heights, axis=0)), 1e-300)
        jump = step > OPEN_DEPTH * width        # from a socket far behind onto the lid
    opening = ~np.isfinite(depth)
    at = np.arange(len(step))[:, None]
    # padding is never steep: a steep stretch reaching a column's last pixel ends there
    steep = (((np.isnan(slope) | (slope > STEEP)) & ~opening[1:]) | opening[:-1]) \
        & (at < length - 1)
    first = np.argmax(steep, axis=0)
    flat = ~steep & (at >= first)
    end = np.where(flat.any(axis=0), np.argmax(flat, axis=0) - 1, length - 2)
    behind = (opening[:-1] | jump) & (at >= first) & (at <= end)
    begin = np.where(behind.any(axis=0), len(step) - np.argmax(behind[::-1], axis=0), first)
    at = np.arange(len(depth))[:, None]
    near = (np.abs(heights - np.take_along_axis(heights, begin[None], axis=0))
            <= NEAR_EDGE * width) & (at >= begin) & (at <= end + 1)
    edge = len(depth) - 1 - np.argmax(near[::-1], axis=0)
    return np.where(steep.any(axis=0), edge, -1)


def _seen_margin(vertices, triangles, opening):
    """(upper ids, lower ids, (upper edge, lower edge), through, how) of the lid margins as seen
    from the front: in every pixel column between the corners, going up (down) from the corners'
    line within EYE_REACH x the width, the vertex nearest the lid's edge (_edge_pixels) where
    that edge is on the front (not a wall deep in a socket seen through the opening); each edge
    (k, 2) the columns' stations and the edge's heights there, by station; through: the share of
    the columns within EYE_STATIONS where both lids' edges are seen. (None, None, None, through,
    why) without two of each."""
    lines, depth, points, triangle = _eye_view(vertices, triangles, opening)
    stations = opening.station(lines[:VIEW_PIXELS])          # the first row: one per column
    heights = opening.height(lines).reshape(VIEW_PIXELS, VIEW_PIXELS)
    columns = np.flatnonzero((stations > 0.05) & (stations < 0.95))
    ahead, edge = [], []
    for sign in (1, -1):
        # each column's pixels within reach, ordered outwards from the corners' line
        height = sign * heights[:, columns]
        within = (height >= 0) & (height <= EYE_REACH * opening.width)
        length = within.sum(axis=0)
        order = np.argsort(np.where(within, height, np.inf), axis=0)[:max(length.max(), 1)]
        ahead.append(order)
        edge.append(_edge_pixels(np.take_along_axis(depth[:, columns], order, axis=0),
                                 np.take_along_axis(heights[:, columns], order, axis=0),
                                 opening.width, length))
    found, edges, through = ([], []), ([], []), []
    for k, column in enumerate(columns):
        seen = 0
        for side, row, edge_points in ((0, found[0], edges[0]), (1, found[1], edges[1])):
            if edge[side][k] < 0:
                continue
            pixel, start = ahead[side][edge[side][k], k], ahead[side][0, k]
            # the column must start in the opening (no surface, or one far behind the lid):
            # where a lid covers the corners' line, the first steep stretch is a crease above
            if triangle[pixel, column] < 0 or \
                    depth[start, column] > depth[pixel, column] - OPEN_DEPTH * opening.width:
                continue
            point = points[pixel, column]
            if opening.depth(point[None])[0] < -LID_DEPTH * opening.width:
                continue        # a steep wall deep in a socket seen through the opening
            corners = triangles[triangle[pixel, column]]
            row.append(corners[np.argmin(np.linalg.norm(vertices[corners] - point, axis=1))])
            edge_points.append((stations[column], heights[pixel, column]))
            seen += 1
        if EYE_STATIONS[0] <= stations[column] <= EYE_STATIONS[-1]:
            through.append(seen == 2)
    through = float(np.mean(through)) if through else 0.0
    upper, lower = (np.unique(np.asarray(row, dtype=np.int64)) for row in found)
    if min(len(upper), len(lower)) < 2:
        return None, None, None, through, \
            "no lid edges seen between the eye's corners (no opening in front)"
    edges = tuple(np.asarray(sorted(points)) for points in edges)
    return upper, lower, edges, through, "seen from the front"


def _opening_ends(vertices, triangles, opening, width=VIEW_WIDTH):
    """((2, 3) the ends of the eye's opening as seen from the front (the first and the second
    corner's side), whether the whole opening was in view), or None where none is seen: the
    connected stretch of a view `width` x the eye's width across with no surface or one more than
    LID_DEPTH x the eye's width behind the corners' line (the hole or the socket behind the
    lids) that covers most of the corners' band (where none does, of those wholly in view, the
    one nearest the corners' middle), its furthest pixels either way along the opening
    (their middle, within a pixel), at the depth of the corners' line."""
    lines, depth, points, triangle = _eye_view(vertices, triangles, opening, width)
    stations = opening.station(lines)
    behind = np.full(len(lines), True)
    seen = triangle.ravel() >= 0
    behind[seen] = opening.depth(points.reshape(-1, 3)[seen]) < -LID_DEPTH * opening.width
    labels, count = ndimage.label(behind.reshape(VIEW_PIXELS, VIEW_PIXELS))
    labels = labels.ravel()
    band = (stations >= 0) & (stations <= 1) & \
        (np.abs(opening.height(lines)) <= EYE_REACH * opening.width)
    covered = np.bincount(labels[band], minlength=count + 1)[1:]
    border = np.zeros((VIEW_PIXELS, VIEW_PIXELS), dtype=bool)
    border[[0, -1]], border[:, [0, -1]] = True, True
    cut = np.bincount(labels[border.ravel()], minlength=count + 1)[1:] > 0
    if covered.any():
        label = 1 + np.argmax(covered)
    elif not cut.all():
        # the corners miss the opening altogether (landmarks on the cheek): the stretch wholly in
        # view nearest their middle (what lies beyond the surface's outline reaches the view's
        # edge)
        middle = np.array([0.5, 0.0])
        apart = np.linalg.norm(np.column_stack([stations, opening.height(lines) / opening.width])
                               - middle, axis=1)
        nearest = ndimage.minimum(apart, labels, np.arange(1, count + 1))
        label = 1 + np.argmin(np.where(cut, np.inf, nearest))
    else:
        return None
    hole = labels == label
    step = width / VIEW_PIXELS            # a pixel, x the eye's width
    ends = [lines[hole & (stations <= stations[hole].min() + step)].mean(axis=0),
            lines[hole & (stations >= stations[hole].max() - step)].mean(axis=0)]
    return np.stack([end - opening.depth(end[None])[0] * opening.forward for end in ends]), \
        not cut[label - 1]


def _visible_edge(ids, opening, vertices, sign):
    """The margin vertices `ids` on the opening's side of their neighbours within EDGE_WINDOW
    stations (sign +1 for the upper lid: the lowest; -1 for the lower lid: the highest) and no
    more than STANDS_OFF beyond the line between their neighbours along the row: where the lid
    occludes the opening from, not the lid's underside or a crease or skin above it."""
    s, h = opening.station(vertices[ids]), sign * opening.height(vertices[ids])
    tolerance = 0.02 * opening.width
    edge = np.array([np.all(h[np.abs(s - s[k]) <= EDGE_WINDOW] >= h[k] - tolerance)
                     for k in range(len(ids))], dtype=bool)
    ids, s, h = (values[edge] for values in (ids, s, h))
    order = np.argsort(s)
    ids, s, h = ids[order], s[order], h[order]
    between = h[:-2] + (h[2:] - h[:-2]) * (s[1:-1] - s[:-2]) / np.maximum(s[2:] - s[:-2], 1e-300)
    beyond = np.concatenate([[0.0], h[1:-1] - between, [0.0]]) if len(ids) >= 3 \
        else np.zeros(len(ids))
    return np.sort(ids[beyond <= STANDS_OFF * opening.width])


def _on_seen_edge(ids, opening, vertices, sign, edge):
    """The margin vertices `ids` no more than OFF_EDGE beyond the lid's `edge` as seen ((k, 2)
    stations and heights, by station) at their station, away from the opening (sign +1 for the
    upper lid, -1 for the lower); those outside the edge's stations are kept (the corners), and
    all of them where fewer than two would be left."""
    s = opening.station(vertices[ids])
    beyond = sign * (opening.height(vertices[ids]) - np.interp(s, edge[:, 0], edge[:, 1]))
    seen = (s >= edge[0, 0]) & (s <= edge[-1, 0])
    kept = ids[~seen | (beyond <= OFF_EDGE * opening.width)]
    return kept if len(kept) >= 2 else ids


def row_heights(opening, points, stations):
    """(S,) the height of a row of margin points at each station (linear between them)."""
    s = opening.station(points)
    order = np.argsort(s)
    return np.interp(stations, s[order], opening.height(points)[order])


def rows_gap(opening, upper, lower, stations):
    """(S,) the upper row's height over the lower row's at each station (rows of points)."""
    return row_heights(opening, upper, stations) - row_heights(opening, lower, stations)


class _Lids:
    """An eye's upper and lower lid edges (rows of vertices) and the gap between them at rest,
    at each of EYE_STATIONS. upper_margin, lower_margin: the rows with the skin beside a coarse
    rim (OFF_EDGE) that the rims pull with it (core.rims). The corners are the landmarks' unless
    they miss the opening (THROUGH): then the ends of the opening as seen from the front."""

    def __init__(self, vertices, triangles, inner, outer, frame):
        self._find(vertices, triangles, _Opening(inner, outer, frame))
        if self.through < THROUGH or self.rest is None or np.any(self.rest <= 0):
            opening, width = self.opening, VIEW_WIDTH
            # at least twice (the second view is centred on the opening), and on until the whole
            # opening is in the eye's view: corners well off it see none or a part of it at
            # first, and a wide view finds it
            for look in range(LOOKS):
                found = _opening_ends(vertices, triangles, opening, width)
                if found is None and width == WIDE_VIEW:
                    return
                if found is not None:
                    ends, whole = found
                    opening = _Opening(*ends, frame)
                    if whole and width == VIEW_WIDTH and look >= 1:
                        break
                width = VIEW_WIDTH if found is not None and found[1] else WIDE_VIEW
            from_corners = dict(vars(self))
            self._find(vertices, triangles, opening)
            if self.rest is None or np.any(self.rest <= 0):      # the ends read no better
                vars(self).clear()
                vars(self).update(from_corners)

    def _find(self, vertices, triangles, opening):
        self.opening = opening
        upper, lower, self.edges, self.through, self.how = _seen_margin(vertices, triangles,
                                                                        opening)
        self.rest = None
        if upper is not None:
            self.upper_margin, self.lower_margin = (
                _visible_edge(row, self.opening, vertices, sign)
                for row, sign in ((upper, 1), (lower, -1)))
            self.upper, self.lower = (
                _on_seen_edge(row, self.opening, vertices, sign, edge) for row, sign, edge
                in zip((self.upper_margin, self.lower_margin), (1, -1), self.edges))
            self.rest = self.gaps(vertices)

    def gaps(self, positions):
        """(S,) height of the upper lid above the lower one at each station (the rest frame's up)."""
        return rows_gap(self.opening, positions[self.upper], positions[self.lower], EYE_STATIONS)

    def find_upper_lid(self, vertices, used):
        """The surface's vertices (`used`) over the opening's upper half at rest (upper_lid):
        within the measured stations (EYE_STATIONS), above the middle between the rows and no
        more than EYE_REACH x the width above it: the upper lid's front, its thickness behind the
        edge and the skin up to the crease."""
        s, h = self.opening.station(vertices[used]), self.opening.height(vertices[used])
        middle = (row_heights(self.opening, vertices[self.upper], s)
                  + row_heights(self.opening, vertices[self.lower], s)) / 2
        self.upper_lid = used[(s >= EYE_STATIONS[0]) & (s <= EYE_STATIONS[-1]) & (h > middle)
                              & (h <= middle + EYE_REACH * self.opening.width)]

    def overrun(self, positions):
        """How far the upper lid (upper_lid) passes below the lower lid's edge at its station
        (the rest frame's up), a share of the mean open height at rest; 0 where it stays above. A
        closing lid meets the lower one; a lid whose thickness or skin is dragged through it
        (the rims hold the edge only) shows below it as a notch."""
        moved = positions[self.upper_lid]
        lower = row_heights(self.opening, positions[self.lower], self.opening.station(moved))
        below = lower - self.opening.height(moved)
        return float(max(below.max(initial=0.0), 0.0) / self.rest.mean())


class Openings:
    """The lids of both eyes on the rest target (or why each is missing) and the face's up."""

    EYE_NAMES = ("eye_inner_{}", "eye_outer_{}")
    NEEDED = tuple(name.format(side) for name in EYE_NAMES for side in EYES) \
        + ("upper_lip", "lower_lip", "nose_tip")

    def __init__(self, vertices, triangles, landmarks):
        """landmarks: {name: target vertex id}."""
        self.lids, self.reasons, self.lips = {}, {}, None
        self._made_on = (vertices, triangles, dict(landmarks))
        points = {name: vertices[i] for name, i in landmarks.items()}
        missing = [name for name in self.NEEDED if name not in points]
        if missing:
            reason = "no landmark " + ", ".join(missing) + " (only automatic landmarks are named)"
            self.reasons = {key: reason for key in ("eye_left", "eye_right", "mouth")}
            return
        frame = FaceAxes(points)
        self.up, self.lips = frame.up, (landmarks["upper_lip"], landmarks["lower_lip"])
        self.rest_lips = self._lips_apart(vertices)
        self.used = np.unique(triangles)        # the surface's vertices, for the lids' own
        for side in EYES:
            lids = _Lids(vertices, triangles, *(points[name.format(side)] for name in self.EYE_NAMES),
                         frame)
            if lids.rest is None:
                self.reasons[f"eye_{side}"] = lids.how
            elif np.any(lids.rest <= 0):
                self.reasons[f"eye_{side}"] = "the eye is closed at rest (no open height)"
            else:
                lids.find_upper_lid(vertices, self.used)
                self.lids[f"eye_{side}"] = lids

    def made_on(self, vertices, triangles, landmarks):
        """Whether these are the openings of this rest surface and these landmarks (so they
        need not be found again)."""
        own_vertices, own_triangles, own_landmarks = self._made_on
        return own_landmarks == landmarks and np.array_equal(own_triangles, triangles) \
            and np.array_equal(own_vertices, vertices)

    def _lips_apart(self, positions):
        upper, lower = self.lips
        return float((positions[upper] - positions[lower]) @ self.up)

    def lip_opening(self, positions):
        """How much further apart the lips stand than at rest, along the face's up: the upper
        and lower lip landmarks (the lips' front-most points on the midline) move with the lips
        however the mouth is modelled (a slit, a pocket, lips merged at rest)."""
        return self._lips_apart(positions) - self.rest_lips


# ------------------------------------------------------------------------------ measures

def measure_expressions(vertices, triangles, deltas, names, landmark_names, landmark_ids,
                        solved_vertices, images=None, openings=None):
    """Measures of every expression on the target: {name: measures}, plus one entry
    "jawOpen+mouthClose" (the two deltas summed) where both are given.

    vertices (n, 3) the rest target; triangles (T, 3) the solved region's triangles (the skin
    the landmarks are on); deltas (E, n, 3); landmark_names/ids: the fit's target landmarks;
    solved_vertices: ids the transfer solved (the rest only follow). Each measures dict holds:
    eyelid_gap_left/right (max over the lid's stations of the gap / the gap at rest; 0 closed,
    1 as at rest, < 0 the lids overlap) and their per-station lists, lid_overrun_left/right (how
    far the upper lid's surface passes below the lower lid's edge, a share of the open height:
    _Lids.overrun), lip_gap (how much further
    apart the lips stand than at rest / the diagonal), edge_stretch (max deformed / rest edge
    length over the solved triangles' edges),
    flipped_triangles (normals turned by more than 90 degrees), motion_outside (max displacement
    outside the solved region / the diagonal), and "<measure>_reason" wherever one is None.
    images: optional (rest (n, 3), deltas (E, n, 3)): the source at each target vertex's
    corresponding point, at rest and moved by each expression (source_images); with them
    excess_stretch is measured too (max over edges of the target's stretch / the source's stretch
    of the same edge's image, counted from 1: what the clone adds to the source's own stretch),
    and excess_flips (the flipped triangles where the source turns over neither their images nor
    those beside them: _Shape._beyond_source), else None. openings: the rest target's Openings
    when found already (the clone's rims find them: CloneResult.openings); found here unless made
    on these vertices, triangles and landmarks.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    deltas = np.asarray(deltas, dtype=np.float64).reshape(-1, len(vertices), 3)
    names = [str(name) for name in names]
    image_rest, image_deltas = (None, None) if images is None else images
    if all(name in names for name in COMBINED):
        together = [names.index(n) for n in COMBINED]
        deltas = np.concatenate([deltas, sum(deltas[k] for k in together)[None]])
        if image_deltas is not None:
            image_deltas = np.concatenate([image_deltas,
                                           sum(image_deltas[k] for k in together)[None]])
        names = names + [MEASURED_TOGETHER]
    if image_deltas is None:
        image_deltas = [None] * len(deltas)
    landmarks = {str(name): int(i) for name, i in zip(landmark_names, landmark_ids)}
    if openings is None or not openings.made_on(vertices, triangles, landmarks):
        openings = Openings(vertices, triangles, landmarks)
    shape = _Shape(vertices, triangles, solved_vertices, image_rest)
    return {name: {**_opening_measures(openings, vertices + delta, shape.diagonal),
                   **shape.measures(delta, image_delta)}
            for name, delta, image_delta in zip(names, deltas, image_deltas)}


def _opening_measures(openings, positions, diagonal):
    """The eyelid gaps (fractions of the rest gap) and the lip gap (fraction of the diagonal)."""
    found = {}
    for side in EYES:
        lids, key = openings.lids.get(f"eye_{side}"), f"eyelid_gap_{side}"
        if lids is None:
            found[key], found[f"{key}_reason"] = None, openings.reasons[f"eye_{side}"]
            found[f"lid_overrun_{side}"] = None
            found[f"lid_overrun_{side}_reason"] = openings.reasons[f"eye_{side}"]
            continue
        fractions = lids.gaps(positions) / lids.rest
        found[key], found[f"{key}_stations"] = float(fractions.max()), fractions.round(4).tolist()
        found[f"lid_overrun_{side}"] = lids.overrun(positions)
    if openings.lips is None:
        found["lip_gap"], found["lip_gap_reason"] = None, openings.reasons["mouth"]
    else:
        found["lip_gap"] = float(openings.lip_opening(positions) / diagonal)
    return found


class _Shape:
    """What an expression does to the solved region's shape and to the rest of the mesh, and
    beyond what its source does at the same place where the source's images are given."""

    def __init__(self, vertices, triangles, solved_vertices, image_rest=None):
        """image_rest (n, 3): the source at each vertex's corresponding point (source_images),
        or None."""
        self.vertices, self.triangles = vertices, triangles
        self.edges = mesh.unique_edges(triangles)
        self.rest_lengths = self._lengths(vertices)
        self.rest_normals = mesh.triangle_normals(vertices, triangles)
        outside = np.ones(len(vertices), dtype=bool)
        outside[np.asarray(solved_vertices, dtype=np.int64)] = False
        self.outside = np.flatnonzero(outside)
        self.diagonal = mesh.diagonal(vertices, np.unique(triangles))
        self.image_rest = image_rest
        if image_rest is not None:
            self.image_rest_lengths = self._lengths(image_rest)
            self.image_rest_normals = mesh.triangle_normals(image_rest, triangles)
            self.beside = triangle_adjacency(triangles)

    def _lengths(self, positions):
        return np.linalg.norm(positions[self.edges[:, 1]] - positions[self.edges[:, 0]], axis=1)

    def measures(self, delta, image_delta=None):
        """The expression `delta` (n, 3)'s edge_stretch, flipped_triangles and motion_outside,
        and with the source's image_delta (n, 3) beside it, _beyond_source's."""
        moved = self.vertices + delta
        lengths = self._lengths(moved)
        usable = self.rest_lengths > 0
        stretch = lengths[usable] / self.rest_lengths[usable]
        flipped = turned_over(self.rest_normals, mesh.triangle_normals(moved, self.triangles))
        outside = np.linalg.norm(delta[self.outside], axis=1).max(initial=0.0)
        return {"edge_stretch": float(stretch.max(initial=1.0)),
                "flipped_triangles": int(flipped.sum()),
                "motion_outside": float(outside / self.diagonal),
                **self._beyond_source(lengths, flipped, image_delta)}

    def _beyond_source(self, lengths, flipped, image_delta):
        """{"excess_stretch", "excess_flips"} of an expression whose edges' lengths (k,) and
        flipped triangles (T,) are given, beside the source's image_delta (n, 3); None (with the
        reason) without images.

        excess_stretch: max over edges of the target's stretch / the source's stretch of the
        edge's image (counted from 1: no less than 1). Raw stretch is no fair bar: real
        expressions stretch the short edges across a lid's or lip's thickness many times
        (MakeHuman's own mouth-open 15x, the library's own jawOpen 37x); what the clone must not
        do is stretch more than its source does at the same place. Edges whose image on the
        source has collapsed to a point (no stretch to compare with) are left out.

        excess_flips: the flipped triangles where the source's expression turns over neither
        their images nor the images of the triangles beside them (source_turns_beside). The
        flipped count's fair bar, as excess_stretch is the stretch's: the library's own jawOpen
        turns 54 triangles of the inner lips over, rolling them into the mouth, and a clone that
        follows it turns their images over too; a finer target's turned stretch ends up to a
        triangle off the source's."""
        if self.image_rest is None:
            reason = "measured only beside the source's expressions"
            return {"excess_stretch": None, "excess_stretch_reason": reason,
                    "excess_flips": None, "excess_flips_reason": reason}
        image_moved = self.image_rest + image_delta
        excess = excess_stretches(self.rest_lengths, lengths, self.image_rest_lengths,
                                  self._lengths(image_moved))
        image_flipped = turned_over(self.image_rest_normals,
                                    mesh.triangle_normals(image_moved, self.triangles))
        beyond = flipped & ~image_flipped & ~source_turns_beside(image_flipped, self.beside)
        return {"excess_stretch": float(excess.max(initial=1.0)),
                "excess_flips": int(beyond.sum())}


def excess_stretches(rest, deformed, image_rest, image_deformed):
    """Each edge's stretch beyond its image's on the source, from the lengths of the edges at
    rest (k,) and deformed (..., k) and of their images at rest (k,) and deformed (..., k): the
    edge's stretch over the image's (counted from 1); 0 where the edge or its image has no
    length (COLLAPSED)."""
    usable = (rest > 0) & (image_rest > COLLAPSED * rest)
    rest, image_rest = np.where(usable, rest, 1.0), np.where(usable, image_rest, 1.0)
    # an edge the source shortens and the clone keeps is not stretched: the source's stretch
    # counts from 1
    return np.where(usable, (deformed / rest) / np.maximum(image_deformed / image_rest, 1.0), 0.0)


def source_turns_beside(image_turned, beside):
    """(k,) bool: the triangles whose neighbours' images the source turns over, from which images
    it turns over (T,) bool and the triangles beside them (k x T, sparse 0/1 rows: rows of
    deformation.triangle_adjacency). A triangle turned over there follows the source's own turn:
    the edge of a turned stretch falls where the target's triangles end, not the source's."""
    return beside @ image_turned.astype(np.float64) > 0


def turned_over(rest_normals, normals):
    """(...) bool: the triangles whose normals (..., 3) turned by more than 90 degrees from their
    rest normals (..., 3): a flipped triangle. Any lengths (the sign alone counts); a triangle
    with no area at rest or moved is not flipped."""
    return np.einsum("...i,...i->...", normals, rest_normals) < 0


def measure_clone(target, result, names=None, deltas=None, source=None, source_deltas=None):
    """measure_expressions of a CloneResult on its target PolyMesh: the solved region is the
    target's parts that hold its landmarks (all of it without landmarks), as in the fit.
    names, deltas: the expressions as written, if not the result's (a subset, or with parts
    kept still). source (PolyMesh) and source_deltas (E, n_source, 3, in the order of `names`):
    the clone's source, for excess_stretch (source_images). Measured on the welded target
    (mesh.welded, as the fit): a lid or lip split at a UV seam is one surface, not a border."""
    names, deltas = (result.names, result.deltas) if names is None else (names, deltas)
    vertices, index, landmarks, region = _solved_region(target, result)
    first = np.unique(index, return_index=True)[1]     # one original of each welded vertex
    images = None if source is None else source_images(vertices, source, source_deltas, result)
    return measure_expressions(vertices, region.triangles, np.asarray(deltas)[:, first], names,
                               result.landmark_names, landmarks, region.used, images,
                               result.openings)


def _solved_region(target, result):
    """(welded vertices, (n,) welded id of each of the target's own vertices, the landmarks'
    welded ids, the Surface of the solved region): the welded target's parts that hold its
    landmarks (all of it without landmarks), as in the fit."""
    welded, index = mesh.welded(target)
    landmarks = index[np.asarray(result.target_landmarks, dtype=np.int64)]
    vertices, triangles = mesh.checked_triangles(welded, "target mesh")
    surface = Surface(vertices, triangles)
    return vertices, index, landmarks, surface.parts_holding(landmarks) if len(landmarks) \
        else surface


def solved_vertices(target, result):
    """(n,) bool: which of the target's (PolyMesh) own vertices lie in the solved region, where
    the clone's motion is the source's carried over. The other parts (a separate eye, lashes,
    teeth, a mouth socket) follow by rules (docs/method.md §9) or stay: they have no counterpart
    on the source, and the source's surface nearest them (source_images) is skin they lie under
    or behind, not a point they correspond to."""
    _, index, _, region = _solved_region(target, result)
    return np.isin(index, region.used)


def source_images(vertices, source, source_deltas, result):
    """(rest (n, 3), deltas (E, n, 3)): the source (PolyMesh, its expressions' deltas) at the
    point of its registered surface (result.registered_source, the source's region: the parts
    holding its landmarks) closest to each target vertex (vertices (n, 3), target coordinates),
    in the source's own coordinates."""
    welded, index = mesh.welded(source)
    first = np.unique(index, return_index=True)[1]
    own, triangles = mesh.checked_triangles(welded, "source mesh")
    landmarks = index[np.asarray(result.source_landmarks, dtype=np.int64)]
    registered = Surface(np.asarray(result.registered_source, dtype=np.float64)[first], triangles)
    if len(landmarks):
        registered = registered.parts_holding(landmarks)
    _, triangle, _, bary = registered.closest(np.asarray(vertices, dtype=np.float64))
    moves = np.moveaxis(np.asarray(source_deltas, dtype=np.float64)[:, first], 0, 1)
    return (interpolate(own, registered.triangles, triangle, bary),
            np.moveaxis(interpolate(moves, registered.triangles, triangle, bary), 1, 0))


BLINKS = {"eyeBlink_L": ("left", "right"), "eyeBlink_R": ("right", "left")}   # closes, stays open
# An expression closes an eye where it leaves less than this share of the eye's open height, and
# opens the mouth where the lips stand this much (x the diagonal) further apart than at rest.
CLOSING = 0.5
OPENING = 0.005


def close_up_expressions(measures, names):
    """(the expression of `names` that closes an eye furthest, the one that opens the mouth
    furthest), each None if none does: what a close-up of the eyes and of the mouth shows,
    whatever the expressions are called. measures: measure_expressions' result."""
    def gap(name):
        gaps = [measures.get(name, {}).get(f"eyelid_gap_{side}") for side in EYES]
        return min((g for g in gaps if g is not None), default=None)

    closing = [(g, name) for g, name in ((gap(name), name) for name in names)
               if g is not None and g < CLOSING]
    opening = [(lip, name) for lip, name in ((measures.get(name, {}).get("lip_gap"), name)
                                             for name in names)
               if lip is not None and lip > OPENING]
    return min(closing)[1] if closing else None, max(opening)[1] if opening else None


def summary(measures):
    """The figures a user reads first, from measure_expressions' result: for each blink the
    closing eye's and the other eye's gap, the lip gap at jawOpen and jawOpen+mouthClose, and
    the worst edge stretch, flipped-triangle counts (all, and beyond the source's) and motion
    outside with their expressions (None where nothing stretched, flipped or moved). A figure
    that cannot be had (no such expression, no lids found) is None."""
    found = {}
    for name, (closing, other) in BLINKS.items():
        row = measures.get(name, {})
        found[f"{name}_gap"] = row.get(f"eyelid_gap_{closing}")
        found[f"{name}_other_eye_gap"] = row.get(f"eyelid_gap_{other}")
    for name in ("jawOpen", MEASURED_TOGETHER):
        found[f"{name}_lip_gap"] = measures.get(name, {}).get("lip_gap")
    # the worst figure's expression is named only where something changed at all
    for key, unchanged in (("edge_stretch", 1.0), ("excess_stretch", 1.0),
                           ("flipped_triangles", 0), ("excess_flips", 0), ("motion_outside", 0.0)):
        known = [name for name in measures if measures[name].get(key) is not None]
        worst = max(known, key=lambda name: measures[name][key], default=None)
        figure = None if worst is None else measures[worst][key]
        found[f"worst_{key}"] = figure
        found[f"worst_{key}_expression"] = worst if figure is not None and figure > unchanged \
            else None
    return found
