"""A character as a target or a source: which of its meshes carries the face, the head region
that is solved (or whose expressions are cloned), and the found face's guidance for the automatic
landmarks (docs/method.md §4, §9).

A character is one or more meshes in one (world) space: a full body with separate eyes, brows
and teeth, a set of objects, or a lone head. The face is found on all of them together
(core.face_finding, by rendering and detecting it); the mesh the found FaceMesh points land on
most often is the face's. Only its head region is solved: the polygons wholly inside the region
make the head mesh given to the engine, and the vertices on the cut (shared with a polygon
outside) are held still, so nothing below the neck moves. A source character (a full body with
expression keys) is cut the same way: its expressions are taken from its head region only, in the
source's own coordinates, with the landmarks found there (source_head).
"""
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from . import face_finding
from .cloning import found_landmarks
from .errors import ExCloneError
from .library import ExpressionLibrary
from .landmarks import NAMES
from .mesh import PolyMesh, diagonal, vertex_parts, welded
from .orientation import FaceFrame

# The automatic landmarks checked against the FaceMesh points: geometry finds these on a head
# like the template's, but on a stylised one (huge eyes, a tiny nose) it can take the wrong
# crease. Further than FAR_FROM_FACEMESH eye distances from FaceMesh's across the face (left-up:
# a point's depth is where its pixel's ray met the surface, which at an eye corner can be the
# eyeball behind the lids), FaceMesh's is taken: the front-most skin vertex within
# ON_THE_RAY eye distances of its ray.
CROSS_CHECKED = ("nose_tip", "nose_bridge", "subnasal", "upper_lip", "lower_lip",
                 "eye_inner_left", "eye_inner_right", "eye_outer_left", "eye_outer_right",
                 "mouth_corner_left", "mouth_corner_right")
FAR_FROM_FACEMESH = 0.2
# The mouth corners are no geometric find but the template's, placed from the others: on a face
# unlike the template (a stylised one's small mouth) they land off the lips, so FaceMesh's are
# taken from its typical error on: 0.07 eye distances on average on ICT faces (face_finding).
TEMPLATE_FAR_FROM_FACEMESH = {"mouth_corner_left": 0.1, "mouth_corner_right": 0.1}
ON_THE_RAY = 0.05

WHAT_TO_DO = ("select the head object, apply its rotation (Object > Apply > Rotation), or place "
              "the landmarks by hand")


@dataclass
class Part:
    """One mesh of a character, in world space."""
    name: str
    mesh: PolyMesh


@dataclass
class FaceGuide:
    """What the found face tells the automatic landmarks, in the target's coordinates."""
    frame: FaceFrame              # the face's own axes (+X left, +Y up, +Z forward)
    points: dict                  # landmark name -> (3,) its FaceMesh point on the surface
                                  # (face_finding.FACEMESH_LANDMARKS)
    eye_distance: float

    def cross_checked(self, names, ids, vertices, candidates):
        """The automatic landmarks (names, ids) with those too far from their FaceMesh point
        (CROSS_CHECKED) and those not found at all replaced by FaceMesh's (the front-most of the
        candidate vertices on its ray); (names in landmarks.NAMES order, ids)."""
        found = dict(zip(names, np.asarray(ids, dtype=np.int64).tolist()))
        flat = self._across(vertices, candidates)
        for name, point in self.points.items():
            known = found.get(name)
            if known is None or (name in CROSS_CHECKED and self._far(vertices[known], point, name)):
                found[name] = self._on_the_ray(point, vertices, candidates, flat)
        kept = [name for name in NAMES if name in found]
        return kept, np.array([found[name] for name in kept], dtype=np.int64)

    def misplaced_nose_tip(self, names, ids, vertices, candidates):
        """FaceMesh's nose tip (a candidate vertex) where the automatic landmarks (names, ids)
        have none or one too far from it, else None. The geometric landmarks are walked from the
        nose tip and the template placed from them, so a wrong tip (a stylised face's lips
        standing out further than its nose) misplaces the mouth, the alar creases and the rest
        with it: they are found again from FaceMesh's."""
        point = self.points.get("nose_tip")
        if point is None:
            return None
        known = dict(zip(names, np.asarray(ids).tolist())).get("nose_tip")
        if known is not None and not self._far(vertices[known], point, "nose_tip"):
            return None
        return self._on_the_ray(point, vertices, candidates, self._across(vertices, candidates))

    def _across(self, vertices, candidates):
        """A KD-tree of the candidate vertices seen along the face's forward axis (left, up)."""
        return cKDTree(vertices[candidates] @ self.frame.rotation[:, :2])

    def _far(self, position, point, name):
        """Whether landmark `name`'s position lies further from its FaceMesh point across the
        face (left-up) than FAR_FROM_FACEMESH (TEMPLATE_FAR_FROM_FACEMESH) eye distances."""
        return np.linalg.norm((position - point) @ self.frame.rotation[:, :2]) \
            > TEMPLATE_FAR_FROM_FACEMESH.get(name, FAR_FROM_FACEMESH) * self.eye_distance

    def _on_the_ray(self, point, vertices, candidates, flat):
        """The front-most candidate within ON_THE_RAY eye distances of the point's ray (along
        the face's forward axis; flat: _across), else the one nearest to the ray."""
        near = flat.query_ball_point(point @ self.frame.rotation[:, :2],
                                     ON_THE_RAY * self.eye_distance)
        if not near:
            near = [flat.query(point @ self.frame.rotation[:, :2])[1]]
        near = candidates[np.asarray(near)]
        return int(near[np.argmax(vertices[near] @ self.frame.rotation[:, 2])])


@dataclass
class HeadCut:
    """The head region of one mesh as a mesh of its own."""
    vertex_ids: np.ndarray        # (m,) the head's vertices in the whole mesh's numbering
    mesh: PolyMesh                # the polygons wholly inside the region, renumbered 0..m-1
    fixed: np.ndarray             # (k,) head vertices on the cut (held still), head numbering
    total: int                    # vertices of the whole mesh
    whole_polygons: tuple         # the whole mesh's (loop_totals, loop_vertices)

    def spread(self, deltas):
        """(E, total, 3) from the head's (E, m, 3): zero outside the head."""
        deltas = np.asarray(deltas)
        whole = np.zeros((len(deltas), self.total, 3), dtype=deltas.dtype)
        whole[:, self.vertex_ids] = deltas
        return whole

    def own_ids(self, ids):
        """Whole-mesh vertex ids of head vertices `ids`."""
        return self.vertex_ids[np.asarray(ids, dtype=np.int64)]

    def head_ids(self, ids):
        """Head numbering of whole-mesh vertex ids, or None if any lies outside the head."""
        ids = np.asarray(ids, dtype=np.int64)
        at = np.searchsorted(self.vertex_ids, ids)
        inside = (at < len(self.vertex_ids)) & (self.vertex_ids[np.minimum(
            at, len(self.vertex_ids) - 1)] == ids)
        return at if inside.all() else None


@dataclass
class CharacterFace:
    """Where a character's face is: the part, its head region and the guide (None when the part
    is used whole, without a found face).

    A found face's head mesh and guide are in the face's own frame (docs/method.md §3: +X the
    character's left, +Y up, +Z forward, about a point of the face; the part's units): the
    engine's size-relative rules (cut-offs against the bounding-box diagonal) then read the same
    whichever way the character stands. `to_world` turns results back."""
    part: int                     # index of the face's Part
    name: str
    head: HeadCut
    guide: FaceGuide
    not_found: str = None         # why rendering found no face, when the part is used whole
    turn: np.ndarray = None       # (3, 3) columns: the frame's axes in world space (None: same)
    origin: np.ndarray = None     # (3,) the frame's origin in world space

    def to_world(self, deltas):
        """(..., 3) displacements in the head mesh's coordinates, in world space."""
        return deltas if self.turn is None else np.asarray(deltas) @ self.turn.T

    def world_points(self, points):
        """(..., 3) positions in the head mesh's coordinates, in world space."""
        return points if self.turn is None else self.to_world(points) + self.origin

    def region(self):
        """What is solved, for a report: "head region: 2,310 of 13,380 vertices"."""
        count, total = len(self.head.vertex_ids), self.head.total
        if self.guide is None:
            return f"whole mesh: {total:,} vertices, no face found by rendering"
        return f"head region: {count:,} of {total:,} vertices"

    def description(self):
        found = "face on" if self.guide is None else "face found on"
        return f"{found} '{self.name}' ({self.region()})"


def whole(part, index, not_found=None):
    """The Part (number `index` of its character) used whole as the head, with no guide: a
    plain head on which no face was found (not_found: the finder's message), or landmarks
    placed outside the found head."""
    n = len(part.mesh.vertices)
    return CharacterFace(index, part.name,
                         HeadCut(np.arange(n), part.mesh, np.zeros(0, dtype=np.int64), n,
                                 (part.mesh.loop_totals, part.mesh.loop_vertices)), None,
                         not_found)


def find(parts):
    """The CharacterFace of a character (a list of Parts in one space): the face found on all
    parts together, the part most of its points land on, that part's head region. ExCloneError
    saying what to do when no face is found."""
    if not parts:
        raise ExCloneError("the character has no mesh to find a face on; " + WHAT_TO_DO)
    triangulated = [part.mesh.triangles() for part in parts]
    vertices, triangles, owner = _together([part.mesh for part in parts], triangulated)
    found = face_finding.find_face(vertices, triangles)
    hits = np.bincount(owner[found.triangle[found.triangle >= 0]], minlength=len(parts))
    if not hits.any():
        raise ExCloneError("the face was seen but lands on no mesh; " + WHAT_TO_DO)
    index = int(np.argmax(hits))
    mesh, own_triangles = parts[index].mesh, triangulated[index]
    first = np.flatnonzero(owner == index)[0]
    on_part = (found.triangle >= first) & (found.triangle < first + len(own_triangles))
    found = replace(found, triangle=np.where(on_part, found.triangle - first, -1))
    region = face_finding.head_region(mesh.vertices, own_triangles, found)
    head = head_cut(mesh, _with_inner_parts(mesh, own_triangles, region))
    if len(head.vertex_ids) == 0:
        raise ExCloneError(f"no head region was found on '{parts[index].name}'; " + WHAT_TO_DO)
    world = guide(found, head.mesh.vertices)
    turn, origin = world.frame.rotation, world.frame.origin
    head.mesh = PolyMesh((head.mesh.vertices - origin) @ turn, head.mesh.loop_totals,
                         head.mesh.loop_vertices)
    own = FaceGuide(FaceFrame(np.eye(3), np.zeros(3), world.frame.diagonal, 0.0),
                    {name: (point - origin) @ turn for name, point in world.points.items()},
                    world.eye_distance)
    return CharacterFace(index, parts[index].name, head, own, turn=turn, origin=origin)


def found_or_whole(parts):
    """find(parts), except that a lone mesh on which no face is found is used whole (the face's
    own geometry then places the landmarks, or says why it cannot)."""
    try:
        return find(parts)
    except ExCloneError as error:
        if len(parts) > 1:
            raise
        return whole(parts[0], 0, not_found=str(error))


def source_head(source, face):
    """The ExpressionLibrary `source` (read whole from one mesh) cut to the head region of the
    CharacterFace found on that mesh, as a target's is: the head's polygons and the expressions'
    motion there, in the source's own coordinates (any motion outside the head is left out),
    the automatic landmarks found on the head with the face's guide (in the face's frame: vertex
    ids do not depend on it), and `head` for mapping the mesh's own vertex ids. A face used whole
    (none found by rendering) leaves the source as it is."""
    if face.guide is None:
        return source
    head = face.head
    names, ids = found_landmarks(head.mesh, "source", face_guide=face.guide)
    mesh = PolyMesh(source.mesh.vertices[head.vertex_ids], head.mesh.loop_totals,
                    head.mesh.loop_vertices)
    return ExpressionLibrary(mesh, list(source.names), source.deltas[:, head.vertex_ids],
                             automatic_landmarks=(list(names), np.asarray(ids, dtype=np.int64)),
                             description=source.description, head=head)


def shared_vertices(source, face):
    """(m,) for each vertex of the face's head, the vertex of the source (an ExpressionLibrary,
    its numbering) that is the same vertex of one base mesh, -1 where the source has none; None
    when the two are not one base mesh. face: the target's CharacterFace. One base mesh: at
    least the source's vertices, and every polygon of the source (cut to a head or not) a polygon
    of the target over the same vertex ids, in the same order (an ICT-FaceKit head and the
    bundled library, also with parts added after its vertices; characters made from one base
    mesh, as MakeHuman's are; not a file whose exporter split vertices at seams, whose numbering
    differs).
    Such a target takes every source triangle's motion on its own triangle, with no registration
    (cloning.fit_faces with these as shared_vertices)."""
    if source.own_vertex_count > face.head.total \
            or len(source.mesh.loop_totals) < MIN_SHARED_POLYGONS:
        return None
    own = source.own_ids(np.arange(len(source.mesh.vertices)))
    loops = own[source.mesh.loop_vertices]
    # one polygon first (cheap: most targets fail here), then all of them
    if not _has_polygon(*face.head.whole_polygons, loops[:source.mesh.loop_totals[0]]) \
            or not _polygons(source.mesh.loop_totals, loops) <= _polygons(
                *face.head.whole_polygons):
        return None
    in_source = np.full(face.head.total, -1)
    in_source[own] = np.arange(len(own))
    return in_source[face.head.vertex_ids]


# Polygons a source must have to be taken for the target's base mesh (a handful could match by
# chance; a face has thousands).
MIN_SHARED_POLYGONS = 100


def _has_polygon(loop_totals, loop_vertices, polygon):
    """Whether the mesh (loop_totals, loop_vertices) has the polygon (its vertex ids in order)."""
    loop_totals, loop_vertices = np.asarray(loop_totals), np.asarray(loop_vertices)
    starts = (np.cumsum(loop_totals) - loop_totals)[loop_totals == len(polygon)]
    matching = starts[loop_vertices[starts] == polygon[0]]
    return any(np.array_equal(loop_vertices[start:start + len(polygon)], polygon)
               for start in matching)


def _polygons(loop_totals, loop_vertices):
    """The set of polygons as tuples of vertex ids (in their own order)."""
    return set(map(tuple, np.split(np.asarray(loop_vertices),
                                   np.cumsum(loop_totals)[:-1])))


def _with_inner_parts(mesh, triangles, region):
    """The head region plus the separate parts of the same mesh (welded: not the pieces of a
    split seam) that lie wholly within its bounding box and outside it (the eyeballs, teeth,
    lashes of a one-mesh head): they are not solved but follow the head in every key
    (docs/method.md §9), as they did before the cut."""
    joined, index = welded(mesh)
    vertices = mesh.vertices
    triangles = index[triangles]
    parts = vertex_parts(len(joined.vertices), triangles)[index]
    low, high = vertices[region].min(axis=0), vertices[region].max(axis=0)
    outside_box = ~np.all((vertices >= low) & (vertices <= high), axis=1)
    count = parts.max() + 1
    inner = (np.bincount(parts, outside_box, count) == 0) & (np.bincount(parts, region, count) == 0)
    used = np.zeros(len(joined.vertices), dtype=bool)
    used[triangles.ravel()] = True
    return region | (inner[parts] & used[index])


def _together(meshes, triangulated):
    """All meshes (and their triangles) as one: (vertices, triangles, (T,) the mesh each
    triangle comes from)."""
    offsets = np.cumsum([0] + [len(mesh.vertices) for mesh in meshes])
    triangles = [own + offset for own, offset in zip(triangulated, offsets)]
    owner = np.repeat(np.arange(len(meshes)), [len(t) for t in triangles])
    return (np.concatenate([mesh.vertices for mesh in meshes]),
            np.concatenate(triangles).astype(np.int64), owner)


def head_cut(mesh, region):
    """HeadCut of a PolyMesh for a (n,) bool vertex mask: the polygons wholly inside it; the
    vertices they share with the polygons outside are the cut, held still."""
    totals = np.asarray(mesh.loop_totals, dtype=np.int64)
    loops = np.asarray(mesh.loop_vertices, dtype=np.int64)
    polygon_of = np.repeat(np.arange(len(totals)), totals)
    inside = np.ones(len(totals), dtype=bool)
    np.logical_and.at(inside, polygon_of, region[loops])
    keep = inside[polygon_of]
    ids = np.unique(loops[keep])
    number = np.full(len(mesh.vertices), -1, dtype=np.int64)
    number[ids] = np.arange(len(ids))
    cut = np.intersect1d(ids, loops[~keep])
    head = PolyMesh(mesh.vertices[ids], totals[inside], number[loops[keep]])
    return HeadCut(ids, head, number[cut], len(mesh.vertices), (totals, loops))


def guide(found, vertices):
    """The FaceGuide of a FoundFace for the head mesh `vertices` (same space): the frame's origin
    on the face's midline, its size the head's."""
    up, forward = np.asarray(found.up, dtype=np.float64), np.asarray(found.forward, dtype=float)
    forward = forward / np.linalg.norm(forward)
    up = up - (up @ forward) * forward
    up /= np.linalg.norm(up)
    left = np.cross(up, forward)          # the character's left (FoundFace's right)
    points = np.asarray(found.points, dtype=np.float64)
    origin = np.nanmean(points, axis=0)   # FaceMesh's points are symmetric about the midline
    frame = FaceFrame(np.stack([left, up, forward], axis=1), origin, diagonal(vertices), 0.0)
    return FaceGuide(frame, found.landmarks(), float(found.eye_distance))

