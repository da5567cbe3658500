"""Landmarks stored with a mesh object, and the editable markers that show them.

Each object keeps its landmarks as ID properties (saved in the .blend): "exclone_landmarks"
{name: vertex id}, "exclone_landmarks_auto" {name: vertex id} as the automatic detector placed
them (to tell edited landmarks from automatic ones) and "exclone_landmarks_vertex_count" (to notice
a mesh edited since). The markers are empties parented to the object, placed at their vertex in
the object's local coordinates (so they follow the object's transform) and tagged with the
landmark's name; the user drags them, Snap puts them back on the nearest vertex and stores the ids.
"""
import bpy
import numpy as np
from scipy.spatial import cKDTree

from ..core.cloning import found_landmarks
from ..core.errors import ExCloneError
from ..core.landmarks import checked_ids
from ..core.mesh import checked_triangles, diagonal
from ..core.orientation import vertex_symmetry_plane
from ..core.reports import listed

IDS = "exclone_landmarks"
AUTOMATIC_IDS = "exclone_landmarks_auto"
VERTEX_COUNT = "exclone_landmarks_vertex_count"
MARKER_TAG = "exclone_landmark"
MARKER_SIZE = 0.012          # x the mesh's bounding-box diagonal
OFF_SURFACE = 1e-4           # a marker further than this x diagonal from its vertex was moved


def detect(mesh, what="mesh"):
    """Automatic landmarks of a PolyMesh exactly as the cloning pipeline finds them: {name: id}."""
    names, ids = found_landmarks(mesh, what)
    return dict(zip(names, (int(i) for i in ids)))


def stored(obj):
    """{name: vertex id} stored on the object ({} if none)."""
    return {name: int(vertex) for name, vertex in obj.get(IDS, {}).items()}


def is_edited(obj):
    return IDS in obj and stored(obj) != {name: int(v) for name, v in obj.get(AUTOMATIC_IDS, {}).items()}


def markers(obj):
    """{landmark name: marker empty} of the object."""
    return {child[MARKER_TAG]: child for child in obj.children if MARKER_TAG in child}


def _vertices(obj):
    me = obj.data
    co = np.empty(len(me.vertices) * 3, dtype=np.float32)
    me.vertices.foreach_get("co", co)
    return co.reshape(-1, 3).astype(np.float64)


def store(obj, landmarks, *, automatic):
    """Store {name: vertex id} on the object and (re)make its markers. automatic=True records them
    as the detector's result too; False keeps the recorded automatic ones (an edit)."""
    obj[IDS] = dict(landmarks)
    if automatic:
        obj[AUTOMATIC_IDS] = dict(landmarks)
    obj[VERTEX_COUNT] = len(obj.data.vertices)
    _make_markers(obj, landmarks)


def clear(obj):
    """Remove the object's landmarks and markers."""
    bpy.data.batch_remove(list(markers(obj).values()))
    for key in (IDS, AUTOMATIC_IDS, VERTEX_COUNT):
        if key in obj:
            del obj[key]


def _make_markers(obj, landmarks):
    vertices = _vertices(obj)
    size = MARKER_SIZE * diagonal(vertices)
    existing = markers(obj)
    bpy.data.batch_remove([m for name, m in existing.items() if name not in landmarks])
    collection = obj.users_collection[0] if obj.users_collection else bpy.context.scene.collection
    for name, vertex in landmarks.items():
        marker = existing.get(name)
        if marker is None:
            marker = bpy.data.objects.new(f"{obj.name} {name}", None)
            collection.objects.link(marker)
            marker[MARKER_TAG] = name
            marker.parent = obj
            marker.empty_display_type = 'SPHERE'
            marker.show_name = True
            marker.show_in_front = True
        marker.matrix_parent_inverse.identity()   # location = the object's local coordinates
        marker.empty_display_size = size
        marker.location = vertices[vertex]


def checked(obj, role):
    """The stored landmarks, after checking they still fit the mesh and sit on their vertices.
    Raises ExCloneError saying what to do otherwise."""
    landmarks = stored(obj)
    count = len(obj.data.vertices)
    placed_on = obj.get(VERTEX_COUNT)
    if placed_on is not None and placed_on != count:
        raise ExCloneError(f"{role} '{obj.name}' has {count} vertices but had {placed_on} when "
                           "its landmarks were placed: run Auto Landmarks again")
    try:
        checked_ids(list(landmarks.values()), count, f"{role} '{obj.name}'")
    except ExCloneError as exc:
        raise ExCloneError(f"{exc}: run Auto Landmarks again, or move its marker and Snap "
                           "Landmarks") from exc
    vertices = _vertices(obj)
    tolerance = OFF_SURFACE * diagonal(vertices)
    moved = [name for name, marker in markers(obj).items()
             if name in landmarks and np.linalg.norm(np.array(marker.location)
                                                     - vertices[landmarks[name]]) > tolerance]
    if moved:
        raise ExCloneError(f"{len(moved)} landmark marker(s) of {role} '{obj.name}' were moved off "
                           f"their vertex ({listed(moved)}): press Snap Landmarks first")
    return landmarks


def snap(obj):
    """Move every marker of the object onto its nearest vertex and store the ids (the landmarks
    whose marker the user deleted are dropped). Returns (names whose vertex changed, dropped)."""
    vertices = _vertices(obj)
    found = markers(obj)
    before = stored(obj)
    names = [name for name in before if name in found] + [n for n in found if n not in before]
    positions = np.array([found[name].location for name in names]).reshape(-1, 3)
    _, nearest = cKDTree(vertices).query(positions)
    landmarks = {name: int(vertex) for name, vertex in zip(names, nearest)}
    obj[IDS] = landmarks
    obj[VERTEX_COUNT] = len(vertices)
    for name, vertex in landmarks.items():
        found[name].location = vertices[vertex]
    return ([name for name in names if before.get(name) != landmarks[name]],
            [name for name in before if name not in landmarks])


def mirrored(obj, mesh, from_side="left"):
    """The object's landmarks with each one of the other side at the mirror image of its
    `from_side` twin, through the face's symmetry plane (core.orientation), snapped to the nearest
    vertex. Returns ({name: id}, names set); the object is not changed."""
    to_side = "right" if from_side == "left" else "left"
    landmarks = stored(obj)
    pairs = [(name, name[:-len(from_side)] + to_side) for name in landmarks
             if name.endswith("_" + from_side) and name[:-len(from_side)] + to_side in landmarks]
    if not pairs:
        return landmarks, []
    normal, offset = vertex_symmetry_plane(*checked_triangles(mesh))
    points = mesh.vertices[[landmarks[a] for a, _ in pairs]]
    reflected = points - 2 * (points @ normal - offset)[:, None] * normal
    _, nearest = cKDTree(mesh.vertices).query(reflected)
    for (_, twin), vertex in zip(pairs, nearest):
        landmarks[twin] = int(vertex)
    return landmarks, [twin for _, twin in pairs]
