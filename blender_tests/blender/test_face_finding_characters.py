"""Finding the face on the shared MakeHuman characters as Blender loads them: whole files (every
mesh object, world space: object transforms applied), full bodies, split seams, FBX's unapplied
rotation and centimetres, a stylised head scaled by 100."""
import numpy as np
import pytest

from blender_tests.helpers.character_files import load_into_scene
from exclone_addon.core import face_finding
from exclone_addon.core.errors import ExCloneError

FILES = ("mh_male_body.blend", "mh_male_body.glb", "mh_female_old_body.fbx", "mh_head_lowpoly.glb",
         "mh_head_dense.blend", "mh_stylised_head.blend", "mh_child_body_expr.blend")
# Every file, as loaded, stands upright (+Z) facing -Y (the characters' README).
FORWARD, UP = np.array([0.0, -1.0, 0.0]), np.array([0.0, 0.0, 1.0])
NOSE_TOLERANCE = 0.15        # eye distances
ANGLE_TOLERANCE = 10.0       # degrees


def _world_mesh(obj):
    """(world-space vertices, triangles) of an object's base mesh."""
    mesh = obj.data
    mesh.calc_loop_triangles()
    vertices = np.empty(len(mesh.vertices) * 3)
    mesh.vertices.foreach_get("co", vertices)
    matrix = np.array(obj.matrix_world)
    triangles = np.empty(len(mesh.loop_triangles) * 3, dtype=np.int64)
    mesh.loop_triangles.foreach_get("vertices", triangles)
    return vertices.reshape(-1, 3) @ matrix[:3, :3].T + matrix[:3, 3], triangles.reshape(-1, 3)


def _character(path):
    """All mesh objects together: vertices, triangles, (T,) object index, object names."""
    objects = sorted((obj for obj in load_into_scene(path).values() if obj.type == 'MESH'),
                     key=lambda obj: obj.name)
    meshes = [_world_mesh(obj) for obj in objects]
    offsets = np.cumsum([0] + [len(v) for v, _ in meshes])
    vertices = np.vstack([v for v, _ in meshes])
    triangles = np.vstack([t + offset for (_, t), offset in zip(meshes, offsets)])
    owner = np.repeat(np.arange(len(meshes)), [len(t) for _, t in meshes])
    return vertices, triangles, owner, [obj.name for obj in objects]


def _angle(a, b):
    return np.degrees(np.arccos(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))


def _true_nose_tip(vertices, skin, found):
    """The skin's most forward vertex (along the known facing) in the middle of the face: within
    0.3 eye distances of the found points' centre sideways (X) and 0.35 up or down (Z): the nose,
    not the lips, which stick out further on some faces."""
    centre = np.nanmean(found.points, axis=0)
    offset = vertices[skin] - centre
    near = skin[(np.abs(offset[:, 0]) < 0.3 * found.eye_distance)
                & (np.abs(offset[:, 2]) < 0.35 * found.eye_distance)]
    return vertices[near[np.argmax(vertices[near] @ FORWARD)]]


@pytest.mark.parametrize("name", FILES)
def test_face_found_on_character(shared_data, name):
    vertices, triangles, owner, names = _character(shared_data / "characters" / name)
    found = face_finding.find_face(vertices, triangles)
    hits = np.bincount(owner[found.triangle[found.hits]], minlength=len(names))
    skin_object = names[int(np.argmax(hits))]
    assert skin_object.startswith(("Body", "Head")), dict(zip(names, hits))
    assert hits.max() > 0.8 * found.hits.sum()
    assert _angle(found.forward, FORWARD) < ANGLE_TOLERANCE
    assert _angle(found.up, UP) < ANGLE_TOLERANCE
    skin = np.unique(triangles[owner == np.argmax(hits)])
    tip = _true_nose_tip(vertices, skin, found)
    nose_error = np.linalg.norm(found.landmarks()["nose_tip"] - tip) / found.eye_distance
    assert nose_error < NOSE_TOLERANCE
    # the head region: on the skin object only, nothing below the cut, the face all in
    region = face_finding.head_region(vertices, triangles, found)
    assert np.all(np.isin(np.flatnonzero(region), skin))
    chin = np.nanmin(found.points @ found.up)          # the face's lowest point (152)
    height = (vertices @ found.up - chin) / found.face_height
    assert np.all(height[region] >= -face_finding.HEAD_CUT_BELOW_CHIN)
    face_vertices = np.unique(triangles[found.triangle[found.hits & np.isin(
        found.triangle, np.flatnonzero(owner == np.argmax(hits)))]])
    assert region[face_vertices].all()
    if name.startswith(("mh_male_body", "mh_female", "mh_child")):
        # a body: the head region stops at the neck, above the shoulders and the hands
        low, high = vertices[skin, 2].min(), vertices[skin, 2].max()
        assert (vertices[region, 2].min() - low) / (high - low) > 0.75


def test_face_found_on_a_body_turned_anyhow(shared_data):
    """A whole body in an orientation no axis view sees face-on, in centimetres: the search
    views follow the body's own axes."""
    from scipy.spatial.transform import Rotation
    vertices, triangles, owner, names = _character(shared_data / "characters" / "mh_male_body.blend")
    rotation = Rotation.from_euler("xyz", [35, -50, 120], degrees=True).as_matrix()
    turned = 100.0 * vertices @ rotation.T
    found = face_finding.find_face(turned, triangles)
    assert _angle(found.forward, rotation @ FORWARD) < ANGLE_TOLERANCE
    assert _angle(found.up, rotation @ UP) < ANGLE_TOLERANCE
    hits = np.bincount(owner[found.triangle[found.hits]], minlength=len(names))
    assert names[int(np.argmax(hits))] == "Body"


def test_no_face_on_a_headless_body(shared_data):
    """A body without its head (the triangles above the neck left out) has no face: refused with
    a message that says what to do, never a face found on a hand or a chest."""
    vertices, triangles, _, _ = _character(shared_data / "characters" / "mh_male_body.blend")
    below_neck = np.all(vertices[triangles][:, :, 2] < 1.55, axis=1)    # the chin is at ~1.63 m
    with pytest.raises(ExCloneError, match="select the head object"):
        face_finding.find_face(vertices, triangles[below_neck])
