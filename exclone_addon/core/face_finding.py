"""Finding the face on any mesh by rendering it and running the face models on the renders
(docs/method.md §4).

Works for a head or a whole character (its objects' world-space meshes concatenated), in any
orientation and units:
1. Search: orthographic renders of the whole mesh along its 3 principal axes both ways and the
   8 diagonals between them (a face turned anywhere is within 55 degrees of one of the 14; the
   axes first: most characters face along one, a body or a mask along its thinnest, a head
   along its depth; the axis its mirror symmetry is across, left to right, last: no face looks
   along it, and on a head it is the thinnest), image up along the longest axis, each turned by
   4 rolls of 90 degrees; BlazeFace runs on the whole image and on a close crop of the
   silhouette's top (on a whole-body view the face is a few dozen pixels: the detector needs it
   closer). A body's longest axis is its height, so one roll has its head at the top. A view
   whose best detection is confident is checked (2.) at once, and the search stops there if it
   passes.
2. Check and refine the best detections: FaceMesh on the view, its points back onto the surface
   through the render's triangle-id buffer, a frame from them (the rotation that lays MediaPipe's
   canonical face onto them), then a close render straight at the face along that frame, detected
   and landmarked again (twice). Detector scores alone prove nothing (views without a face still
   score up to ~0.7): a face is accepted on FaceMesh's presence and a re-detection on the close
   render, both high, and on points that are not a mirror image of the face: an open surface (a
   face mask, a scan) seen from behind shows its hollow inside, which the models take for a
   face (the hollow-face illusion) with its left and right swapped.
3. The result: the 468 FaceMesh points on the surface (and their triangles), the face's axes and
   its eye distance.
"""
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from . import data, face_models
from .errors import ExCloneError
from .face_render import Camera, Render, render
from .mesh import PolyMesh, triangle_areas, vertex_normals, vertex_parts, welded
from .orientation import mirror_errors, surface_samples

RENDER_SIZE = 512
# Whole-mesh views, as coefficients of three axes (the mesh's principal axes in the order of
# _search_axes): the 6 axis directions first (the third axis both ways first), then the 8
# diagonals.
SEARCH_DIRECTIONS = (np.repeat(np.eye(3)[::-1], 2, axis=0) * np.tile([[1], [-1]], (3, 1)),
                     np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T / np.sqrt(3.0))
# Share of the silhouette's height taken as the close crop of its top: a standing body's head
# and neck (a body is ~7.5 heads tall), upright in one of the four rolls.
TOP_CROP = 0.25
# Detections (of the search) refined before giving up; they are tried best first.
CANDIDATES = 4
# A view's best detection scoring this much is refined at once (a face seen well: the other
# views are not rendered if it passes); the others wait for the whole search's ranking.
CONFIDENT = 0.8
REFINEMENTS = 2
# Surface points mirrored to find the axis the mesh is symmetric across (_search_axes).
SYMMETRY_SAMPLES = 3000
# Acceptance on the close render: FaceMesh's presence and BlazeFace's score there. Measured:
# faces (the shared heads, bodies, ICT faces) re-detect at 0.87-0.95 with presence 1.000; the
# best non-face that got that far (the back of a head) re-detected at 0.59, presence 0.19.
MIN_PRESENCE = 0.9
MIN_REDETECTION = 0.75
# The close render is this many face heights (forehead 10 to chin 152) across.
CLOSE_VIEW_FACES = 1.6
# FaceMesh points used for the frame and the sizes.
FOREHEAD, CHIN = 10, 152       # CHIN: the chin's lowest point (the menton)
EYE_CORNERS_RIGHT, EYE_CORNERS_LEFT = (33, 133), (263, 362)   # the character's right, left
# The project's landmark names (core.landmarks.NAMES; "left" is the character's left) at the
# FaceMesh point nearest each: measured on the ICT library's face and three ICT identities
# against the library's automatic landmarks, within 0.07 eye distances on average (0.2 at worst:
# the outer eye corners and upper lids, where a ray can meet the eyeball behind the lids).
# The project's chin is the chin's front (FaceMesh 200), not its lowest point (152, the menton:
# 0.33 eye distances away); its eye_inner points lie on the lower lid next to the corners.
# Brow points are left out: FaceMesh's brow row runs ~0.1 eye distances from the template's.
FACEMESH_LANDMARKS = {
    "nose_tip": 4, "nose_bridge": 8, "subnasal": 164, "alar_left": 331, "alar_right": 102,
    "upper_lip": 0, "lower_lip": 16, "chin": 200, "eye_inner_left": 382, "eye_inner_right": 155,
    "eye_outer_left": 263, "eye_outer_right": 33, "mouth_corner_left": 291,
    "mouth_corner_right": 61, "eyelid_upper_left": 386, "eyelid_upper_right": 27,
    "jaw_left": 397, "jaw_right": 172,
}
NOT_FOUND = ("no face found on the mesh; select the head object, apply its rotation "
             "(Object > Apply > Rotation & Scale), or place the landmarks by hand")


@dataclass(frozen=True)
class FoundFace:
    """A face found on a mesh, in the mesh's (world) space.

    right, up, forward: the face's own axes, a right-handed frame (the canonical frame of
    docs/method.md §3: right is the viewer's right looking at the face, i.e. the character's
    left; forward points out of the face)."""
    points: np.ndarray     # (468, 3) FaceMesh points on the surface, NaN where one missed
    triangle: np.ndarray   # (468,) the triangle each point lies on, -1 where it missed
    right: np.ndarray
    up: np.ndarray
    forward: np.ndarray
    eye_distance: float    # between the eye centres (mid-corners), on the surface
    face_height: float     # forehead (10) to chin (152) on the surface (if either missed: the
                           # canonical face's, scaled to the points)
    presence: float        # FaceMesh's face presence on the final close render
    detection: float       # BlazeFace's score on the final close render
    search_score: float    # BlazeFace's score on the search view that led here

    @property
    def frame(self):
        """(3, 3) rotation: columns right, up, forward."""
        return np.column_stack([self.right, self.up, self.forward])

    @property
    def hits(self):
        return self.triangle >= 0

    def landmarks(self):
        """{project landmark name: (3,) point} for the FACEMESH_LANDMARKS points that hit."""
        return {name: self.points[i] for name, i in FACEMESH_LANDMARKS.items()
                if self.triangle[i] >= 0}


@dataclass(frozen=True)
class _Candidate:
    score: float
    view: Render
    detection: face_models.FaceDetection   # in the view's own pixels


class _Models:
    """The detector and the landmarker, loaded once per search (cv2.dnn nets are not shared
    between threads)."""

    def __init__(self):
        self.detector = face_models.FaceDetector()
        self.landmarker = face_models.FaceLandmarker()
        self.canonical = data.canonical_face().vertices


def find_face(vertices, triangles):
    """The face on a mesh (world-space (n, 3) vertices, (m, 3) triangles): a FoundFace.

    Raises ExCloneError (saying what to do) when no view holds a face that passes the checks."""
    vertices = np.asarray(vertices, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    if len(triangles) == 0 or not np.all(np.isfinite(vertices)):
        raise ExCloneError("the mesh has no triangles or non-finite vertices; " + NOT_FOUND)
    normals = _shading_normals(vertices, triangles)
    models = _Models()
    axes = _principal_axes(vertices, triangles)
    search_axes = _search_axes(vertices, triangles, axes)
    # the checks on the close render are strict: the first candidate passing them is it
    for directions in SEARCH_DIRECTIONS:
        candidates, tried = [], []
        for view_candidates in _search(vertices, triangles, normals, models,
                                       directions @ search_axes, axes[0]):
            candidates += view_candidates
            best = max(view_candidates, key=lambda c: c.score, default=None)
            if best is not None and best.score >= CONFIDENT:
                # a face seen this well is refined before rendering the other views
                tried.append(best)
                found = _refined(vertices, triangles, normals, models, best)
                if found is not None:
                    return found
        for candidate in sorted(candidates, key=lambda c: -c.score)[:CANDIDATES]:
            found = None if any(candidate is t for t in tried) else \
                _refined(vertices, triangles, normals, models, candidate)
            if found is not None:
                return found
    raise ExCloneError(NOT_FOUND)


def _shading_normals(vertices, triangles):
    """Vertex normals of the mesh welded at split seams (so seams do not show as creases in the
    renders), given back per original vertex."""
    joined, index = welded(PolyMesh.from_faces(vertices, triangles))
    return vertex_normals(joined.vertices, index[triangles])[index]


def _principal_axes(vertices, triangles):
    """(3, 3) rows: the surface's principal axes, longest first (area-weighted triangle centres,
    so a densely meshed face does not pull them)."""
    centres = vertices[triangles].mean(axis=1)
    area = triangle_areas(vertices, triangles)
    weights = area / area.sum() if area.sum() > 0 else np.full(len(area), 1.0 / len(area))
    spread = centres - weights @ centres
    _, vectors = np.linalg.eigh((spread * weights[:, None]).T @ spread)
    return vectors[:, ::-1].T


def _search_axes(vertices, triangles, axes):
    """The principal axes `axes` (rows, longest first) as SEARCH_DIRECTIONS takes them (the
    third row's views first, the first row's last): first the axis the mesh is mirror-symmetric
    across (mirrored through its centre across it, the surface lands on itself best: its left to
    right), then the other two, longest first. A face looks along one of those two: a head along
    its depth (its width, the thinnest, is left to right), a body or a mask along its thinnest."""
    samples, _ = surface_samples(vertices, triangles, count=SYMMETRY_SAMPLES)
    across = int(np.argmin(mirror_errors(cKDTree(samples), samples.mean(axis=0), axes, samples)))
    others = [k for k in range(3) if k != across]           # longest first
    return axes[[across] + others]


def _whole_view(vertices, direction, longest):
    """A camera that sees the whole mesh from `direction`, image up along the `longest` axis
    (or, looking along it, along another)."""
    up = longest - direction * np.dot(longest, direction)
    if np.linalg.norm(up) < 1e-6:
        up = np.cross(direction, np.eye(3)[np.argmin(np.abs(direction))])
    probe = Camera.looking(np.zeros(3), direction, up, 1.0, RENDER_SIZE)
    local = vertices @ probe.axes[:2].T
    low, high = local.min(axis=0), local.max(axis=0)
    centre = probe.axes[:2].T @ ((low + high) / 2.0)
    width = 1.05 * float(np.max(high - low))
    return Camera.looking(centre, direction, up, max(width, 1e-12), RENDER_SIZE)


def _search(vertices, triangles, normals, models, directions, longest):
    """Per view from these directions (one at a time, rendered when asked for): the
    detections in every roll and crop of it."""
    for direction in directions:
        view = render(vertices, triangles, _whole_view(vertices, direction, longest), normals)
        candidates = []
        for roll in range(4):
            image = _turned(view.image, roll)
            for crop_image, offset in _crops(image):
                for detection in models.detector.detect(crop_image):
                    unrolled = _unrolled(detection, offset, roll, RENDER_SIZE)
                    candidates.append(_Candidate(detection.score, view, unrolled))
        yield candidates


def _turned(image, roll):
    """The image turned `roll` quarter turns clockwise."""
    codes = (cv2.ROTATE_90_CLOCKWISE, cv2.ROTATE_180, cv2.ROTATE_90_COUNTERCLOCKWISE)
    return image if roll == 0 else cv2.rotate(image, codes[roll - 1])


def _crops(image):
    """The whole image and a square crop of its silhouette's top: (image, (x, y) offset)."""
    yield image, np.zeros(2)
    rows = np.flatnonzero(image.any(axis=(1, 2)))
    if len(rows) == 0:
        return
    side = max(int(TOP_CROP * (rows[-1] - rows[0] + 1)), face_models.MIN_FACE_PIXELS)
    top = rows[0]
    columns = np.flatnonzero(image[top:top + side].any(axis=(0, 2)))
    middle = (columns[0] + columns[-1]) // 2
    left = int(np.clip(middle - side // 2, 0, image.shape[1] - side))
    yield image[top:top + side, left:left + side], np.array([left, top], float)


def _unrolled(detection, offset, roll, size):
    """A detection made in a crop (at offset) of the render turned `roll` quarter turns
    clockwise, in the unturned render's pixels."""
    def back(points):
        points = np.asarray(points, float) + offset
        for _ in range(roll):       # undo one clockwise quarter turn: (x, y) <- (y, size-1-x)
            points = np.column_stack([points[:, 1], size - 1 - points[:, 0]])
        return points

    corners = back(detection.box.reshape(2, 2))
    box = np.concatenate([corners.min(axis=0), corners.max(axis=0)])
    return face_models.FaceDetection(box=box, score=detection.score,
                                     keypoints=back(detection.keypoints))


def _landmarks_on_surface(view, models, roi):
    """FaceMesh on a render: (468, 3) surface points, (468,) triangles, presence."""
    pixels, presence = models.landmarker.landmarks(view.image, roi)
    points, ids = view.surface_points(pixels[:, :2])
    return points, ids, presence


def _frame(points, canonical):
    """(rotation (3, 3) with columns right, up, forward; face height) that lay the canonical
    face onto the points found (NaN ones left out); None if too few. The face height (forehead
    to chin) is the canonical face's, scaled to the points."""
    hit = np.all(np.isfinite(points), axis=1)
    if hit.sum() < face_models.NUM_LANDMARKS // 2:
        return None
    world = points[hit] - points[hit].mean(axis=0)
    model = canonical[hit] - canonical[hit].mean(axis=0)
    rotation, _ = Rotation.align_vectors(world, model)
    scale = np.sqrt((world ** 2).sum() / (model ** 2).sum())
    return rotation.as_matrix(), float(scale * np.linalg.norm(canonical[FOREHEAD] - canonical[CHIN]))


def _refined(vertices, triangles, normals, models, candidate):
    """The candidate checked by FaceMesh and refined by close renders; None if it is no face."""
    points, ids, presence = _landmarks_on_surface(
        candidate.view, models, face_models.roi_from_detection(candidate.detection))
    if presence < face_models.FACE_PRESENCE_THRESHOLD:
        return None
    detection_score = 0.0
    for _ in range(REFINEMENTS):
        fitted = _frame(points, models.canonical)
        if fitted is None:
            return None
        rotation, height = fitted
        centre = np.nanmean(points, axis=0)
        camera = Camera.looking(centre, rotation[:, 2], rotation[:, 1],
                                CLOSE_VIEW_FACES * height, RENDER_SIZE)
        view = render(vertices, triangles, camera, normals)
        roi, detection_score = _close_roi(view, models, points)
        points, ids, presence = _landmarks_on_surface(view, models, roi)
    fitted = _frame(points, models.canonical)
    if fitted is None or presence < MIN_PRESENCE or detection_score < MIN_REDETECTION \
            or _mirrored(points, models.canonical):
        return None
    return _found(points, ids, fitted, presence, detection_score, candidate.score)


def _mirrored(points, canonical):
    """Whether the surface points found (NaN where missed) are a mirror image of the canonical
    face: the linear map that best lays the canonical face onto them turns it inside out
    (negative determinant). Measured, over the cube of the points' size: the ICT face region (an
    open mask) found from behind -1.00; faces found from the front 0.76-1.02 (the seven shared
    characters, the ICT head, the demo head, the mask)."""
    hit = np.all(np.isfinite(points), axis=1)
    model = canonical[hit] - canonical[hit].mean(axis=0)
    linear = np.linalg.lstsq(model, points[hit] - points[hit].mean(axis=0), rcond=None)[0]
    return np.linalg.det(linear) < 0


def _close_roi(view, models, points):
    """The FaceMesh region on a close render and BlazeFace's score there: the detection nearest
    the image centre if there is one, else the previous points' region."""
    detections = models.detector.detect(view.image)
    centre = np.full(2, (view.camera.size - 1) / 2.0)
    if detections:
        best = min(detections, key=lambda d: np.linalg.norm((d.box[:2] + d.box[2:]) / 2 - centre))
        return face_models.roi_from_detection(best), best.score
    projected = view.camera.project(points[np.all(np.isfinite(points), axis=1)])
    return face_models.roi_from_landmarks(projected[:, :2]), 0.0


def _found(points, ids, fitted, presence, detection_score, search_score):
    def mid(pair):
        return np.nanmean(points[list(pair)], axis=0)

    rotation, fitted_height = fitted
    eye_distance = float(np.linalg.norm(mid(EYE_CORNERS_LEFT) - mid(EYE_CORNERS_RIGHT)))
    face_height = float(np.linalg.norm(points[FOREHEAD] - points[CHIN]))
    if not np.isfinite(face_height):
        face_height = fitted_height
    return FoundFace(points=points, triangle=ids, right=rotation[:, 0], up=rotation[:, 1],
                     forward=rotation[:, 2], eye_distance=eye_distance, face_height=face_height,
                     presence=presence, detection=detection_score, search_score=search_score)


def head_region(vertices, triangles, found):
    """(n,) bool: the head, for a solve that must leave the rest of a character still.

    The mesh (welded at split seams) is cut by a plane HEAD_CUT_BELOW_CHIN face heights below
    the chin (the face's lowest FaceMesh point, 152), perpendicular to the face's up axis; of
    the connected pieces above the cut, those holding at least MIN_PART_SHARE of the best
    piece's hits: the skin (eyes, teeth and lashes hold a few hits and are left out; a raised
    hand above the cut holds none). `found` must index these triangles."""
    vertices = np.asarray(vertices, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    joined, index = welded(PolyMesh.from_faces(vertices, triangles))
    joined_triangles = index[triangles]
    hit_vertices = np.unique(index[triangles[found.triangle[found.hits]]].ravel())
    chin = np.nanmin(found.points @ found.up)         # point 152, or the lowest that hit
    above = vertices @ found.up - chin >= -HEAD_CUT_BELOW_CHIN * found.face_height
    above_joined = np.zeros(len(joined.vertices), dtype=bool)
    above_joined[index[above]] = True
    kept = joined_triangles[np.all(above_joined[joined_triangles], axis=1)]
    labels = vertex_parts(len(joined.vertices), kept)
    counts = np.bincount(labels[hit_vertices], minlength=labels.max() + 1)
    counts[labels[np.setdiff1d(np.arange(len(labels)), np.unique(kept))]] = 0   # lone vertices
    chosen = counts >= MIN_PART_SHARE * counts.max()
    return chosen[labels[index]] & above


# Below the chin point, in face heights (forehead 10 to chin 152): the head region keeps the
# under-chin and the upper neck, which jawOpen and the mouth shapes move (below it the library's
# jawOpen moves at most 5% of its peak), and stops where the shoulders start on the shared
# bodies (0.25-0.3 face heights below the chin; docs/method.md §4).
HEAD_CUT_BELOW_CHIN = 0.3
# A piece is part of the head when it holds at least this share of the best piece's hit
# vertices: the skin holds hundreds, an eyeball or the lashes a few dozen.
MIN_PART_SHARE = 0.25
