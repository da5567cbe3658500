"""What follows the face (docs/method.md §9): eyes, eyebrows and eyelashes, teeth and tongue.

The engine solves the skin; everything else a character has at its face (eyeballs, eyebrow and
eyelash cards, teeth, gums, tongue), as separate parts of the target mesh or as objects of their
own, follows the solved skin by rules a rigged character obeys:

- **eyes** (a closed, roughly spherical shell in an eye socket) stay rigid with the skull in
  every key, except the eyeLook* keys of their side, where they turn about their fitted centre
  by EYE_LOOK_DEGREES (the skin keys move the lids on top);
- **brows, lashes and shells on the eye** (on the skin or just off it) hang from their points
  touching the skin, which move with their closest skin point, turning with its triangle (a
  brow raise lifts the brows, a blink closes the lashes and the shells with the lids);
- **teeth and tongue** (inside the mouth, behind the lips): the lower row and the tongue move
  with the jaw, a rigid motion about its joint fitted per key to the skin around the chin; gums
  holding both rows are cut between them, a tongue inside them found; the upper row stays
  with the skull; in tongueOut the tongue also comes forward out of the opened mouth;
- anything else (glasses, hair, a prop, a far object) stays still.

Pure numpy/scipy; positions and displacements in one (world) space, in and out.
"""
from dataclasses import dataclass

import numpy as np
from scipy.sparse.csgraph import (breadth_first_order, connected_components, dijkstra,
                                  maximum_flow)
from scipy.sparse import coo_matrix, csr_matrix
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from . import face_render
from .errors import ExCloneError
from .mesh import PolyMesh, unique_edges, vertex_parts, welded
from .surface import Surface

EYE, SKIN, MOUTH, STILL = "eye", "skin", "mouth", "still"
UPPER, LOWER, TONGUE = 0, 1, 2

# Gaze angles at an eyeLook* key's full value. ARKit documents neither the angles nor their
# limits; apps that turn eye bones from these keys use about 30 degrees at 1.0 (e.g. kmp-facelink's
# GazeEstimator: "ARKit eye look blend shapes typically saturate around 30-35 degrees"), and the
# human eye's range is smaller upward than downward (about 25 against 30 degrees of comfortable
# gaze), so up is a little less.
EYE_LOOK_DEGREES = {"In": 30.0, "Out": 30.0, "Up": 25.0, "Down": 30.0}

# The face's scale for every rule below is the distance between the outer eye corners (the eye
# span, ~9 cm on an adult): rules then read the same on a child, a giant or a model in cm.
# An eye: a sphere fitted to the piece (least squares) with a radius of 5-30% of the eye span
# (a real eyeball is ~13%, a cartoon's larger), vertices within 12% of the radius of it (a cornea
# bulges ~8%), vertices all around it (some vertex beyond 40% of the radius in each of the face's
# six directions: a shell round its centre, not a cap or a card; MakeHuman's eyeball is open at
# the back, reaching 53% there), centred within 35% of the span of the middle of an eye's
# corners (the eyeball sits ~13% behind them).
EYE_RADIUS = (0.05, 0.30)
EYE_SPHERE_FIT = 0.12
EYE_SHELL = 0.4
EYE_SOCKET_REACH = 0.35
# The mouth's inside: a piece centred behind the lips (0.1 span in front to 0.9 behind), within
# half a span of the midline and of the lips' height. Teeth and tongue sit 1-6 cm behind the lips.
MOUTH_BOX = {"left": 0.5, "up": 0.5, "front": 0.1, "back": 0.9}
# A piece whose vertices lie (median) within 10% of the span of the skin is on it: eyebrows sit
# ~1-2 mm off the skin, lashes grow from the lid margin with tips ~1 cm out.
SKIN_HUG = 0.10
# The points of such a piece within 1% of the span of the skin (beyond its nearest: touching it,
# under a millimetre on an adult) are its roots (a lash card's base on the lid margin, most of a
# brow); the rest hang from them.
ROOT_GAP = 0.01
# A hanging point takes every root of its part up to a few HANG_BLEND of the span farther than
# its nearest, weighed by a Gaussian of that extra distance (a lash tip: the stretch of margin
# at its card's base; a shell's point over the eye's opening: both lids). Against MakeHuman's
# own refit of a child's lashes in its eye closure: mean error 33-38% of the motion (36-39%
# from the nearest root alone, 74% from each point's own closest skin point), brows 8-14%
# (9-15%). ICT-FaceKit's head through the registration, eyeBlink_L: error max 0.46 of the
# lashes' largest motion and 0.51 of the eye shells' (0.73 and 0.67 from the nearest root,
# whose neighbours on a card each turned another way: edges stretched 3.4x and 8.6x, shards).
HANG_BLEND = 0.01
# The jaw's rigid motion is fitted to the skin within 30% of the span of the chin point and more
# than 35% of the span below the lips' line: the chin carries the bone's motion, the lips and
# cheeks deform on their own. The jaw moves in a key only if that patch moves as one body (the
# fit's residual under 8% of the patch's motion): measured on a MakeHuman head, jawOpen, jawLeft,
# jawRight and jawForward leave 2.6-4.9%, keys that only slide the skin (smiles, puffs, presses)
# 10-64%.
JAW_PATCH = (0.30, 0.35)
JAW_RIGIDITY = 0.08
# The jaw turns about its joints in front of the ears: ICT-FaceKit's jawOpen turns its lower teeth
# by 25 degrees about the face's left axis (rigid to 0.3%) through a point 0.36 of the span above
# the mouth and 1.11 behind it. The chin's skin turns less than the bone and slides (fitted freely,
# 7.5 degrees), which sent the lower molars 3.05 cm where they go 1.89; so the fit also holds that
# joint still, weighted as 5% of the patch. Given the library's own skin motion, its teeth's error
# against its own: jawOpen max 1.33 -> 0.77 cm (peak 4.13; mean 0.29 -> 0.27: the chin still turns
# less than the bone), jawForward mean 0.12 -> 0.04 (peak 0.90), jawLeft 0.10 -> 0.05 (0.74).
# Through the registration (a renumbered library head): jawOpen teeth max 1.17 -> 0.78 cm,
# jawForward's mean 0.08 -> 0.07 but its max 0.18 -> 0.23 (a quarter of the patch: 0.25; the
# joint slides forward there).
JAW_JOINT = (0.36, 1.11)
JAW_JOINT_WEIGHT = 0.05
# A mouth part that holds the teeth of both rows (gums and palate in one piece) is split vertex
# by vertex: the teeth are planted in it, their centres (median, per row) within 4.5% of the span
# of it. MakeHuman's gums: 3.0-3.2%; its tongue, which the lower teeth stand beside: 5.6-7.1%.
GUMS_HOLD = 0.045
# Such a part is cut between the rows where the fewest surface is cut (a minimum cut of its edge
# graph, capacities the edges' lengths) between the vertices the teeth of each row are planted in:
# those within 2% of the span of a tooth, taking its row. ICT-FaceKit's one part of gums, palate,
# throat, floor and tongue: the cut runs round the tongue's root and behind the last molars as
# the library's own jawOpen does (8 of its 2,977 vertices kept up that move, 38 moved that stay);
# the bite plane, point by point, sent the palate's back and the throat down (218 and 49).
GUMS_PLANTED = 0.02
# A tongue: a mouth part below the bite plane, across the midline, at least a quarter of the eye
# span deep (a tongue is ~80%, a tooth ~8%), whose vertices near the midline (within 10% of its
# width) run along more than 60% of its depth; a row of teeth is an arch, open behind the front.
TONGUE_DEPTH = 0.25
TONGUE_MIDLINE = (0.10, 0.60)
# Without a tongue of its own, the tongue is sought in a part holding both rows (ICT-FaceKit's
# gums, palate, throat, floor and tongue are one): among the vertices that go with the jaw, those
# seen from above (the top of the jaw's side, not its underside), nearer the midline than the
# lower tooth nearest them (inside the arch), and more than 8% of the span along the surface
# from where the lower teeth are planted (not the gums round them); their largest connected
# piece, if it is a tongue by the rule above. On the library's own mesh: its dorsum from the
# root to behind the incisors, 137 vertices, all moving with its jaw, 0.68 of the span deep.
TONGUE_OFF_TEETH = 0.08
# "Seen from above": an orthographic render looking down, at most this fraction of the span per
# pixel (half a millimetre on an adult).
SEEN_PIXEL = 0.005
# tongueOut: the skin opens its jaw by this fraction of jawOpen (Apple's reference shape shows the
# mouth half open) and the tongue, moved with the jaw, comes straight forward until its tip
# stands a quarter of its own depth in front of the lips (~2 cm on an adult, as a tongue
# stuck out does).
TONGUE_OUT_JAW_OPEN = 0.5
TONGUE_OUT_REACH = 0.25
# A follower key that moves no vertex by more than this fraction of the span is not worth a key
# (a millimetre on an adult, not seen): the lower teeth get jawOpen but not eyeBlink.
KEY_MIN_MOTION = 0.01

# the face points the rules need, by the engine's landmark names (core/landmarks.py)
FACE_POINTS = ("eye_outer_left", "eye_outer_right", "eye_inner_left", "eye_inner_right",
               "nose_bridge", "upper_lip", "lower_lip", "chin")


@dataclass
class Face:
    """The solved skin at rest and the face's own axes and points, in the caller's space."""
    skin: Surface
    left: np.ndarray              # unit: towards the character's left
    up: np.ndarray
    forward: np.ndarray           # out of the face
    mouth: np.ndarray             # between the lips
    chin: np.ndarray
    eyes: np.ndarray              # (2, 3) middle of the left and of the right eye's corners
    span: float                   # outer eye corner to outer eye corner

    def local(self, points):
        """(m, 3) points as (left, up, forward) coordinates about the mouth."""
        return (np.asarray(points) - self.mouth) @ np.stack([self.left, self.up, self.forward]).T


def face_from_points(skin_vertices, skin_triangles, points):
    """Face of the solved skin (vertices, triangles) and its named points {name: (3,)}.
    ExCloneError naming what is missing when the points do not describe a face."""
    missing = [name for name in FACE_POINTS if name not in points]
    if missing:
        raise ExCloneError("the parts around the face cannot be placed without the face's points "
                           f"({', '.join(missing)}); run Auto Landmarks on the face")
    p = {name: np.asarray(points[name], dtype=np.float64) for name in FACE_POINTS}
    across = p["eye_outer_left"] - p["eye_outer_right"]
    span = float(np.linalg.norm(across))
    if span == 0:
        raise ExCloneError("the face's outer eye corners coincide; check the landmarks")
    left = across / span
    up = p["nose_bridge"] - p["chin"]
    up = up - left * (up @ left)
    up /= np.linalg.norm(up)
    eyes = np.stack([(p["eye_outer_left"] + p["eye_inner_left"]) / 2,
                     (p["eye_outer_right"] + p["eye_inner_right"]) / 2])
    return Face(Surface(skin_vertices, skin_triangles), left, up, np.cross(left, up),
                (p["upper_lip"] + p["lower_lip"]) / 2, p["chin"], eyes, span)


@dataclass
class Piece:
    """A group of a follower's parts that moves by one rule."""
    kind: str                     # EYE, SKIN, MOUTH or STILL
    ids: np.ndarray               # vertex ids of the follower
    side: int = 0                 # eyes: 0 left, 1 right
    centre: np.ndarray = None     # eyes: fitted centre
    roles: np.ndarray = None      # mouth: UPPER, LOWER or TONGUE per vertex of ids


@dataclass
class Following:
    """A follower's motion: deltas (E, m, 3) and the pieces it was cut into (their ids in the
    follower's welded numbering)."""
    deltas: np.ndarray
    pieces: list

    def kinds(self):
        """What its pieces are, for a report: e.g. ["eye"], ["skin"], ["teeth", "tongue"]."""
        kinds = set()
        for piece in self.pieces:
            if piece.kind == MOUTH:
                kinds.update(["tongue"] if (piece.roles == TONGUE).any() else [])
                kinds.update(["teeth"] if (piece.roles != TONGUE).any() else [])
            elif piece.kind != STILL:
                kinds.add(piece.kind)
        return sorted(kinds)

    def moving_keys(self, names, span):
        """The names of the keys that move a vertex by more than KEY_MIN_MOTION of the span."""
        reach = np.linalg.norm(self.deltas, axis=2).max(axis=1, initial=0.0)
        return [name for name, r in zip(names, reach) if r > KEY_MIN_MOTION * span]


def follow(face, skin_deltas, names, meshes):
    """The motion of each follower in every key: a Following per mesh, deltas (E, m, 3).

    meshes: [(vertices (m, 3), triangles (t, 3)), ...] at rest: the separate objects of a
    character, or the parts of the target mesh the skin does not hold. skin_deltas: (E, n, 3) of
    the face's skin vertices. The teeth of every mesh together set the bite plane (upper and
    lower rows may be objects of their own)."""
    skin_deltas = np.asarray(skin_deltas, dtype=np.float64)
    meshes = _welded_pieces(face, meshes)
    _set_roles(face, meshes)
    followings = []
    for vertices, triangles, index, mine in meshes:
        deltas = np.zeros((len(names), len(vertices), 3))
        for piece in mine:
            points = vertices[piece.ids]
            if piece.kind == EYE:
                deltas[:, piece.ids] = _eye_motion(face, names, points, piece)
            elif piece.kind == SKIN:
                parts = vertex_parts(len(vertices), triangles)[piece.ids]
                deltas[:, piece.ids] = _skin_motion(face, skin_deltas, points, parts)
            elif piece.kind == MOUTH:
                deltas[:, piece.ids] = _mouth_motion(face, skin_deltas, names, points,
                                                     piece.roles, _within(triangles, piece.ids))
        followings.append(Following(deltas[:, index], mine))
    return followings


def on_solved_parts(face, deltas, names, vertices, triangles):
    """(E, n, 3) what the rules add to a mesh's separate parts (`triangles` over `vertices`, n)
    that already move by `deltas` (E, n, 3, the skin's too, in the face's skin numbering): in a
    target of the source's own base mesh the transfer moves every part as the source's moves
    (docs/method.md §7), and a source's eyes and tongue may not do what ARKit's keys ask (the
    library's eyeLook keys move the lids only; its tongueOut is made from jawOpen). So an eye the
    key leaves still turns in its eyeLook keys, and a tongue comes forward in tongueOut
    (TONGUE_OUT_REACH), as follow() moves the parts it places. Zero elsewhere."""
    deltas = np.asarray(deltas, dtype=np.float64)
    if not len(triangles):
        return np.zeros((len(names), len(vertices), 3))
    meshes = _welded_pieces(face, [(vertices, triangles)])
    points, triangles, index, pieces = meshes[0]
    added = np.zeros((len(names), len(points), 3))
    # each welded vertex's motion: that of one of its copies
    copy = np.zeros(len(points), dtype=np.int64)
    copy[index] = np.arange(len(index))
    for piece in (p for p in pieces if p.kind == EYE):
        turn = _eye_motion(face, names, points[piece.ids], piece)
        left_still = np.linalg.norm(deltas[:, copy[piece.ids]], axis=2).max(axis=1) \
            < KEY_MIN_MOTION * face.span
        for e in np.flatnonzero(left_still):
            added[e, piece.ids] = turn[e]
    mouth = [p for p in pieces if p.kind == MOUTH]
    if not mouth or not any(name.endswith("tongueOut") for name in names):
        return added[:, index]
    _set_roles(face, meshes)
    for piece in mouth:
        added[:, piece.ids] = _tongue_out_motion(face, deltas, names, points[piece.ids],
                                                 piece.roles, _within(triangles, piece.ids),
                                                 deltas[:, copy[piece.ids]])
    return added[:, index]


def _welded_pieces(face, meshes):
    """Each mesh (vertices, triangles) at rest welded (copies split at UV seams, glTF and FBX,
    are one vertex for the rules, and move alike) and cut into its classified pieces:
    [(vertices, triangles, the welded id of each of its own vertices, pieces)]."""
    welded_meshes = []
    for vertices, triangles in meshes:
        weld, index = _welded(vertices, triangles)
        points, joined = weld.vertices, weld.triangles()
        welded_meshes.append((points, joined, index, [_classified(face, points, ids)
                                                      for ids in _pieces(points, joined)]))
    return welded_meshes


def _set_roles(face, meshes):
    """The roles of the mouth pieces of every mesh (_welded_pieces): the teeth of all of them
    together set the bite plane (upper and lower rows may be objects of their own)."""
    _set_mouth_roles(face, [(vertices[p.ids], _within(triangles, p.ids), p)
                            for vertices, triangles, _, pieces in meshes
                            for p in pieces if p.kind == MOUTH])


def _welded(vertices, triangles):
    """(welded PolyMesh, (m,) welded id of every vertex) of a triangle mesh (mesh.welded)."""
    triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    return welded(PolyMesh(np.asarray(vertices, dtype=np.float64),
                           np.full(len(triangles), 3), triangles.ravel()))


def _within(triangles, ids):
    """The triangles whose corners are all in `ids`, numbered by position in `ids` (sorted)."""
    kept = triangles[np.isin(triangles, ids).all(axis=1)]
    return np.searchsorted(ids, kept)


# ------------------------------------------------------------------------------ pieces

def _pieces(vertices, triangles):
    """Vertex ids of each piece: connected parts, a part whose bounding box lies inside another's
    (a cornea in its eyeball, a tooth in the gums, a tongue between them) joined to it."""
    triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    used = np.unique(triangles)
    parts = vertex_parts(len(vertices), triangles)[used]
    labels = np.unique(parts)
    low = np.array([vertices[used[parts == label]].min(axis=0) for label in labels])
    high = np.array([vertices[used[parts == label]].max(axis=0) for label in labels])
    margin = 0.1 * (high - low)
    inside = np.all((low[:, None] >= low[None] - margin[None])
                    & (high[:, None] <= high[None] + margin[None]), axis=2)
    a, b = np.nonzero(inside)
    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(len(labels),) * 2)
    groups = connected_components(graph, directed=False)[1]
    group_of = groups[np.searchsorted(labels, parts)]
    return [used[group_of == g] for g in np.unique(group_of)]


def _classified(face, vertices, ids):
    """The Piece of the vertices `ids`: an eye, the mouth's inside, on the skin, or still."""
    points = vertices[ids]
    eye = _as_eye(face, points)
    if eye is not None:
        return Piece(EYE, ids, side=eye[0], centre=eye[1])
    local = face.local(points.mean(axis=0)) / face.span
    box = MOUTH_BOX
    if abs(local[0]) < box["left"] and abs(local[1]) < box["up"] \
            and -box["back"] < local[2] < box["front"]:
        return Piece(MOUTH, ids)
    distances = face.skin.closest(points)[2]
    if np.median(distances) < SKIN_HUG * face.span:
        return Piece(SKIN, ids)
    return Piece(STILL, ids)


def _as_eye(face, points):
    """(side, centre) if the points are an eyeball's shell in an eye socket, else None."""
    if len(points) < 10:
        return None
    centre, radius = _fitted_sphere(points)
    if not EYE_RADIUS[0] * face.span <= radius <= EYE_RADIUS[1] * face.span:
        return None
    offsets = points - centre
    lengths = np.linalg.norm(offsets, axis=1)
    if np.sqrt(np.mean((lengths - radius) ** 2)) > EYE_SPHERE_FIT * radius:
        return None
    axes = np.stack([face.left, face.up, face.forward])
    reach_out = np.concatenate([(offsets @ axes.T).max(axis=0), -(offsets @ axes.T).min(axis=0)])
    if reach_out.min() < EYE_SHELL * radius:
        return None
    reach = np.linalg.norm(face.eyes - centre, axis=1)
    side = int(np.argmin(reach))
    return (side, centre) if reach[side] < EYE_SOCKET_REACH * face.span else None


def _fitted_sphere(points):
    """(centre, radius) of the least-squares sphere through the points (|x|^2 = 2 c.x + k)."""
    mean = points.mean(axis=0)
    x = points - mean
    system = np.column_stack([2 * x, np.ones(len(x))])
    solution = np.linalg.lstsq(system, (x ** 2).sum(axis=1), rcond=None)[0]
    centre = solution[:3]
    return centre + mean, float(np.sqrt(max(solution[3] + centre @ centre, 0.0)))


# ------------------------------------------------------------------------------ eyes

def eye_look(name):
    """(side, direction) of an eyeLook* key name ('eyeLookIn_L' -> (0, 'In'); after a prefix
    too, as Clone's Prefix option writes them), else None."""
    for direction in EYE_LOOK_DEGREES:
        for side, suffix in enumerate(("_L", "_R")):
            if name.endswith(f"eyeLook{direction}{suffix}"):
                return side, direction
    return None


def gaze_rotation(face, side, direction):
    """The Rotation that turns an eye of `side` (0 left, 1 right) by its eyeLook key: In turns
    the eye towards the nose, Out away from it."""
    degrees = EYE_LOOK_DEGREES[direction]
    if direction in ("Up", "Down"):
        # turning about -left carries forward towards up
        axis = -face.left if direction == "Up" else face.left
    else:
        # turning about up carries forward towards left: out for the left eye, in for the right
        outward = 1.0 if side == 0 else -1.0
        axis = face.up * (outward if direction == "Out" else -outward)
    return Rotation.from_rotvec(np.radians(degrees) * axis)


def _eye_motion(face, names, points, piece):
    """(E, m, 3): still, but turned about the centre in the eyeLook keys of its side."""
    motion = np.zeros((len(names), len(points), 3))
    for e, name in enumerate(names):
        look = eye_look(name)
        if look is not None and look[0] == piece.side:
            turned = gaze_rotation(face, *look).apply(points - piece.centre) + piece.centre
            motion[e] = turned - points
    return motion


# ------------------------------------------------------------------------------ skin-bound

def _skin_motion(face, skin_deltas, points, parts):
    """(E, m, 3): each point is carried by its roots' closest skin points and turns with those
    skin triangles. Roots are the points within ROOT_GAP of the skin (of their connected part;
    its nearest points if none is); every other point hangs from the roots of its part, each
    weighed by how much farther it is than the nearest (a Gaussian of HANG_BLEND): a lash's tip
    swings with the lid margin its base sits on instead of sliding with the skin under it, its
    neighbours on the card hang from the same stretch of margin (not each from another root
    turning its own way: shards), and a shell over the eye's opening closes with both lids
    instead of tearing between them."""
    skin = face.skin
    nearest, triangle, distance, bary = skin.closest(points)
    blend = HANG_BLEND * face.span
    nearest_root = np.zeros(len(points))
    point, root = [], []            # each point's roots, pair by pair
    for part in np.unique(parts):
        mine = np.flatnonzero(parts == part)
        rooted = mine[distance[mine] <= distance[mine].min() + ROOT_GAP * face.span]
        tree = cKDTree(points[rooted])
        nearest_root[mine] = tree.query(points[mine])[0]
        reach = nearest_root[mine] + 3 * blend
        for i, near in zip(mine, tree.query_ball_point(points[mine], reach)):
            point.append(np.full(len(near), i))
            root.append(rooted[near])
    point, root = np.concatenate(point), np.concatenate(root)
    beyond = np.linalg.norm(points[point] - points[root], axis=1) - nearest_root[point]
    closeness = np.exp(-(beyond / blend) ** 2)
    hang = coo_matrix((closeness / np.bincount(point, closeness, len(points))[point],
                       (point, np.arange(len(point)))), (len(points), len(point))).tocsr()
    corners = skin.triangles[triangle[root]]                                # (pairs, 3)
    offsets = points[point] - nearest[root]
    rest = _triangle_frames(skin.vertices[corners])                         # (pairs, 3, 3)
    motion = np.zeros((len(skin_deltas), len(points), 3))
    for e, deltas in enumerate(skin_deltas):
        carried = np.einsum("pc,pcx->px", bary[root], deltas[corners])
        moved = _triangle_frames(skin.vertices[corners] + deltas[corners])
        turned = np.einsum("pij,pkj,pk->pi", moved, rest, offsets)          # R = F' F^T
        motion[e] = hang @ (carried + turned - offsets)
    return motion


def _triangle_frames(corners):
    """(..., 3, 3) orthonormal frames (columns: first edge, normal, their cross) of triangles."""
    edge = corners[..., 1, :] - corners[..., 0, :]
    normal = np.cross(edge, corners[..., 2, :] - corners[..., 0, :])
    edge = edge / np.maximum(np.linalg.norm(edge, axis=-1, keepdims=True), 1e-300)
    normal = normal / np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-300)
    return np.stack([edge, normal, np.cross(edge, normal)], axis=-1)


# ------------------------------------------------------------------------------ mouth

def _set_mouth_roles(face, mouth):
    """Set every mouth piece's roles (UPPER, LOWER or TONGUE per vertex): each part by its centre
    against the bite plane, a part holding the teeth of both rows (gums) vertex by vertex.
    mouth: [(vertices, triangles, Piece)]."""
    # every part of every piece: (piece, its vertices' mask, their face coordinates)
    parts = []
    for vertices, triangles, piece in mouth:
        labels, local = vertex_parts(len(vertices), triangles), face.local(vertices)
        for label in np.unique(labels):
            mine = labels == label
            parts.append((piece, mine, local[mine], _within(triangles, np.flatnonzero(mine))))
    centres = np.array([local.mean(axis=0) for _, _, local, _ in parts]).reshape(-1, 3)
    plane = _bite_plane(centres)
    below = centres[:, 1] < plane(centres)
    for _, _, piece in mouth:
        piece.roles = np.full(len(piece.ids), UPPER)
    both_rows = []       # the parts holding both rows: (piece, their ids in it, ...)
    for k, (piece, mine, local, triangles) in enumerate(parts):
        others = np.flatnonzero(np.arange(len(centres)) != k)
        if _holds_both_rows(face, local, centres[others], below[others]):
            planted = _planted(face, local, [parts[j][2] for j in others], below[others])
            piece.roles[mine] = _rows_cut(face, local, triangles, planted, plane)
            both_rows.append((piece, np.flatnonzero(mine), local, triangles, planted))
        elif below[k]:
            piece.roles[mine] = TONGUE if _is_tongue(face, local) else LOWER
    if any((piece.roles == TONGUE).any() for _, _, piece in mouth):
        return
    for piece, ids, local, triangles, planted in both_rows:
        tongue = _tongue_within(face, local, triangles, piece.roles[ids] == LOWER, planted)
        piece.roles[ids[tongue]] = TONGUE


def _planted(face, local, others, others_below):
    """(lower, upper, lower teeth points): the vertices of a part (face coordinates `local`) the
    teeth of each row are planted in (within GUMS_PLANTED of a tooth, taking the row of the
    nearest: `others` the other mouth parts' points, below the bite plane or not), and the lower
    row's points."""
    points = np.concatenate(others)
    rows = np.repeat(others_below, [len(p) for p in others])
    distance, nearest = cKDTree(points).query(local)
    planted = distance < GUMS_PLANTED * face.span
    return (np.flatnonzero(planted & rows[nearest]), np.flatnonzero(planted & ~rows[nearest]),
            points[rows])


def _rows_cut(face, local, triangles, planted, plane):
    """(m,) UPPER or LOWER per vertex of a part holding the teeth of both rows (face coordinates
    `local`, its `triangles`, `planted` as _planted gives): the side of the minimum cut (edge
    lengths) between the vertices each row's teeth are planted in. The gums of both rows, the
    palate, the throat and the floor of the mouth meet far behind the teeth, where the palate
    dips below the bite plane: the plane alone sent ICT's palate and throat down with the jaw.
    Without planted teeth of both rows, the bite plane decides."""
    lower, upper, _ = planted
    if not len(lower) or not len(upper):
        return np.where(local[:, 1] < plane(local), LOWER, UPPER)
    edges, lengths = _edges(local, triangles)
    # integer capacities (scipy's maximum_flow): lengths in 1e-4 of the span, at least 1
    capacity = np.maximum(np.rint(lengths / face.span * 1e4), 1).astype(np.int64)
    n = len(local)
    source, sink, unbounded = n, n + 1, int(2 * capacity.sum() + 1)
    tails = np.concatenate([edges[:, 0], edges[:, 1], np.full(len(lower), source), upper])
    heads = np.concatenate([edges[:, 1], edges[:, 0], lower, np.full(len(upper), sink)])
    capacities = np.concatenate([capacity, capacity, np.full(len(lower) + len(upper), unbounded)])
    graph = csr_matrix((capacities.astype(np.int32), (tails, heads)), shape=(n + 2, n + 2))
    residual = (graph - maximum_flow(graph, source, sink).flow).tocsr()
    residual.data = np.where(residual.data > 0, residual.data, 0)
    residual.eliminate_zeros()
    jawed = np.zeros(n + 2, dtype=bool)
    jawed[breadth_first_order(residual, source, directed=True, return_predecessors=False)] = True
    return np.where(jawed[:n], LOWER, UPPER)


def _tongue_within(face, local, triangles, jawed, planted):
    """(m,) mask of the tongue in a part holding both rows (face coordinates `local`, its
    `triangles`; `jawed` its vertices that go with the jaw; `planted` as _planted gives): see
    TONGUE_OFF_TEETH. None of them if no such piece is a tongue."""
    lower, _, lower_teeth = planted
    none = np.zeros(len(local), dtype=bool)
    if not len(lower) or not jawed.any():
        return none
    off_teeth = _along_surface(local, triangles, lower) > TONGUE_OFF_TEETH * face.span
    inside = np.abs(local[:, 0]) < np.abs(lower_teeth[cKDTree(lower_teeth).query(local)[1], 0])
    candidate = jawed & off_teeth & inside \
        & _seen_from_above(face, local, triangles[jawed[triangles].all(axis=1)])
    if not candidate.any():
        return none
    parts = vertex_parts(len(local), triangles[candidate[triangles].all(axis=1)])
    tongue = candidate & (parts == np.bincount(parts[candidate]).argmax())
    return tongue if _is_tongue(face, local[tongue]) else none


def _seen_from_above(face, local, triangles):
    """(m,) whether each vertex (face coordinates) is a corner of a triangle seen from above (an
    orthographic render looking down the face's up axis, SEEN_PIXEL of the span per pixel)."""
    seen = np.zeros(len(local), dtype=bool)
    if not len(triangles):
        return seen
    used = local[np.unique(triangles)]
    width = 1.05 * max(np.ptp(used[:, 0]), np.ptp(used[:, 2]))
    size = int(np.clip(np.ceil(width / (SEEN_PIXEL * face.span)), 16, 1024))
    camera = face_render.Camera.looking((used.min(axis=0) + used.max(axis=0)) / 2,
                                        np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0]),
                                        width, size=size)
    shown = face_render.render(local, triangles, camera, shaded=False).triangle
    seen[triangles[np.unique(shown[shown >= 0])].ravel()] = True
    return seen


def _along_surface(points, triangles, ids):
    """(m,) each point's distance from the nearest of the points `ids` along the triangles'
    edges (inf where none is connected to it)."""
    edges, lengths = _edges(points, triangles)
    graph = coo_matrix((lengths, (edges[:, 0], edges[:, 1])), shape=(len(points),) * 2).tocsr()
    return dijkstra(graph, directed=False, indices=ids, min_only=True)


def _edges(local, triangles):
    """((k, 2) the triangles' edges, once each; (k,) their lengths)."""
    edges = unique_edges(triangles)
    return edges, np.linalg.norm(local[edges[:, 0]] - local[edges[:, 1]], axis=1)


def _holds_both_rows(face, local, other_centres, other_below):
    """Whether a part (face coordinates) holds the teeth of both rows, as gums and palate in
    one piece do: the other parts' centres of each row lie (median) within GUMS_HOLD of it."""
    if not other_below.any() or other_below.all():
        return False
    reach = cKDTree(local).query(other_centres)[0]
    return bool(np.median(reach[other_below]) < GUMS_HOLD * face.span
                and np.median(reach[~other_below]) < GUMS_HOLD * face.span)


def _bite_plane(centres):
    """The bite plane in face coordinates about the mouth, from the mouth parts' centres: a
    callable giving its height under points (k, 3). With 4 parts or more, the plane fitted
    through their centres (upper and lower rows balance each other, and the plane tilts back
    with the arch as the rows do); else the lips' line."""
    if len(centres) < 4:
        return lambda points: np.zeros(len(points))
    system = np.column_stack([np.ones(len(centres)), centres[:, 0], centres[:, 2]])
    a, b, c = np.linalg.lstsq(system, centres[:, 1], rcond=None)[0]
    return lambda points: a + b * points[:, 0] + c * points[:, 2]


def _is_tongue(face, local):
    """A part (face coordinates) that crosses the midline and runs along it for a quarter of the
    eye span or more: not a tooth, not an arch of teeth."""
    width, depth = np.ptp(local[:, 0]), np.ptp(local[:, 2])
    if not local[:, 0].min() < 0 < local[:, 0].max() or depth < TONGUE_DEPTH * face.span:
        return False
    midline = local[np.abs(local[:, 0]) <= TONGUE_MIDLINE[0] * width]
    return len(midline) > 1 and np.ptp(midline[:, 2]) > TONGUE_MIDLINE[1] * depth


def _mouth_motion(face, skin_deltas, names, points, roles, triangles):
    """(E, m, 3): upper row still, lower row and tongue with the jaw, the tongue forward in
    tongueOut (the piece's `triangles` numbered as its points)."""
    motion = np.zeros((len(names), len(points), 3))
    jawed = roles != UPPER
    if not jawed.any():
        return motion
    patch = _jaw_patch(face)
    rest = face.skin.vertices[patch]
    if len(patch) >= 3:
        for e in range(len(names)):
            motion[e, jawed] = _jaw_motion(face, rest, skin_deltas[e, patch], points[jawed])
    motion += _tongue_out_motion(face, skin_deltas, names, points, roles, triangles, motion)
    return motion


def _tongue_out_motion(face, skin_deltas, names, points, roles, triangles, moved):
    """(E, m, 3) what the tongueOut keys add to a mouth piece (its points at rest, their roles,
    its triangles; moved by `moved` (E, m, 3) already, the jaw opened): the tongue
    _tongue_out's translation, the rest of the piece that translation times _tongue_weights;
    zero in other keys."""
    added = np.zeros_like(moved)
    tongue = roles == TONGUE
    keys = [e for e, name in enumerate(names) if name.endswith("tongueOut")]
    if not tongue.any() or not keys:
        return added
    weights = _tongue_weights(face, points, roles, triangles)
    for e in keys:
        added[e] = weights[:, None] * _tongue_out(face, skin_deltas[e],
                                                  points[tongue] + moved[e, tongue])
    return added


def _tongue_weights(face, points, roles, triangles):
    """(m,) how much of the tongue's translation each point of a mouth piece takes: 1 on the
    tongue; on the rest of the jaw's side of a piece the tongue is cut from (ICT-FaceKit's one
    surface of floor and tongue), falling smoothly to 0 over TONGUE_OFF_TEETH of the span along
    the surface, so the floor round the tongue's root and sides comes with it instead of
    tearing along the tongue's outline (it ends before the lower teeth's gums); 0 elsewhere."""
    tongue = roles == TONGUE
    weights = tongue.astype(np.float64)
    jawed = np.flatnonzero(roles == LOWER)
    if not len(jawed) or not len(triangles):
        return weights
    along = _along_surface(points, triangles, np.flatnonzero(tongue))[jawed]
    near = np.clip(1.0 - along / (TONGUE_OFF_TEETH * face.span), 0.0, 1.0)
    weights[jawed] = near * near * (3.0 - 2.0 * near)          # smoothstep
    return weights


def _tongue_out(face, skin_deltas, tongue):
    """(3,) the translation along forward that brings the tongue's tip (positions `tongue`,
    the jaw opened) TONGUE_OUT_REACH of its depth in front of the lips (the skin within 30% of
    the span of the mouth, moved by the key)."""
    near = np.linalg.norm(face.skin.vertices - face.mouth, axis=1) < 0.3 * face.span
    lips_front = ((face.skin.vertices[near] + skin_deltas[near]) @ face.forward).max(initial=0.0)
    reach = tongue @ face.forward
    return max(lips_front + TONGUE_OUT_REACH * np.ptp(reach) - reach.max(), 0.0) * face.forward


def _jaw_patch(face):
    """Skin vertex ids that carry the jaw's motion: around the chin, below the lips (fewer than
    3: the skin has no chin, the jaw does not move)."""
    ids = face.skin.used
    near = np.linalg.norm(face.skin.vertices[ids] - face.chin, axis=1) < JAW_PATCH[0] * face.span
    below = face.local(face.skin.vertices[ids])[:, 1] < -JAW_PATCH[1] * face.span
    return ids[near & below]


def _jaw_motion(face, rest, moves, points):
    """(m, 3) the motion of `points` with the jaw: if the patch (rest positions, `moves`) moves
    as one body (the rigid motion that best carries it leaves under JAW_RIGIDITY), the rigid
    motion that best carries the patch and holds the jaw's joint (JAW_JOINT) still, weighted
    as JAW_JOINT_WEIGHT of the patch; else none."""
    if not moves.any():
        return np.zeros_like(points)
    rotation, centre, moved_centre = _rigid_fit(rest, rest + moves, np.ones(len(rest)))
    residual = rotation.apply(rest - centre) + moved_centre - rest - moves
    if np.sqrt(np.mean(residual ** 2)) >= JAW_RIGIDITY * np.sqrt(np.mean(moves ** 2)):
        return np.zeros_like(points)
    joint = face.mouth + face.span * (JAW_JOINT[0] * face.up - JAW_JOINT[1] * face.forward)
    anchored = np.vstack([rest, joint])
    rotation, centre, moved_centre = _rigid_fit(
        anchored, anchored + np.vstack([moves, np.zeros(3)]),
        np.append(np.ones(len(rest)), JAW_JOINT_WEIGHT * len(rest)))
    return rotation.apply(points - centre) + moved_centre - points


def _rigid_fit(rest, moved, weights):
    """(Rotation, rest centre, moved centre) of the weighted rigid motion that best carries the
    points `rest` to `moved` (Kabsch, Rotation.align_vectors)."""
    centre = np.average(rest, axis=0, weights=weights)
    moved_centre = np.average(moved, axis=0, weights=weights)
    rotation = Rotation.align_vectors(moved - moved_centre, rest - centre, weights=weights)[0]
    return rotation, centre, moved_centre
