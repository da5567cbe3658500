"""Finding the face on a mesh by rendering it (core.face_render, core.face_finding): the renderer's
id buffer and depth order, the face and its frame on heads in any orientation and units, the
FaceMesh points' landmark names, the head region."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from exclone_addon.core import data, face_finding, face_render
from exclone_addon.core.errors import ExCloneError
from exclone_addon.core.library import load_library
from exclone_addon.core.mesh import PolyMesh, vertex_parts

# The nose tip FaceMesh gives (point 4, the project's nose_tip) must be this close to the
# geometric one, and the frame this close to the truth.
NOSE_TOLERANCE = 0.15        # eye distances
ANGLE_TOLERANCE = 10.0       # degrees


def _square(z, size=1.0):
    """Two triangles covering [-size, size]^2 at height z, wound towards +z."""
    v = np.array([[-size, -size, z], [size, -size, z], [size, size, z], [-size, size, z]])
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def _angle(a, b):
    return np.degrees(np.arccos(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))


def test_render_keeps_the_nearest_triangle_and_its_id():
    far_v, far_t = _square(0.0, 1.0)
    near_v, near_t = _square(0.5, 0.5)
    vertices = np.vstack([far_v, near_v])
    triangles = np.vstack([far_t, near_t + 4])
    camera = face_render.Camera.looking(np.zeros(3), (0, 0, 1), (0, 1, 0), 4.0, size=64)
    view = face_render.render(vertices, triangles, camera)
    centre, corner, outside = view.triangle[32, 32], view.triangle[18, 18], view.triangle[2, 2]
    assert centre in (2, 3)          # the near square, in front of the far one
    assert corner in (0, 1)          # only the far square covers this pixel
    assert outside == -1 and not view.image[2, 2].any()
    assert view.image[32, 32].any()
    # flipped windings render the same (two-sided): a mesh exported inside out still shows
    flipped = face_render.render(vertices, triangles[:, ::-1], camera)
    assert np.array_equal(flipped.triangle >= 0, view.triangle >= 0)
    assert np.array_equal(flipped.image, view.image)


def test_surface_points_lie_on_the_triangle_seen():
    vertices, triangles = _square(0.25)
    camera = face_render.Camera.looking((0.1, 0.0, 0.0), (0, 0, 1), (0, 1, 0), 4.0, size=64)
    view = face_render.render(vertices, triangles, camera)
    pixels = np.array([[31.5, 31.5], [40.2, 20.7], [1.0, 1.0], [np.nan, 3.0], [500.0, 3.0]])
    points, ids = view.surface_points(pixels)
    assert np.all(ids[:2] >= 0) and np.all(ids[2:] == -1)
    assert np.all(np.isnan(points[2:]))
    assert np.allclose(points[:2, 2], 0.25)
    # the point is where the pixel's ray meets the surface: it projects back onto the pixel
    assert np.allclose(camera.project(points[:2])[:, :2], pixels[:2], atol=1e-9)


def _nose_tip(vertices, ids, found, forward):
    """The most forward vertex (along the true forward) of `ids` near the middle of the face
    the found points span: within 0.3 eye distances of their centre sideways, 0.35 up or down
    (the nose, not the lips, which stick out further on some faces)."""
    centre = np.nanmean(found.points, axis=0)
    up = found.up - forward * np.dot(found.up, forward)
    up /= np.linalg.norm(up)
    right = np.cross(up, forward)
    offset = vertices[ids] - centre
    near = ids[(np.abs(offset @ right) < 0.3 * found.eye_distance)
               & (np.abs(offset @ up) < 0.35 * found.eye_distance)]
    return vertices[near[np.argmax(vertices[near] @ forward)]]


@pytest.fixture(scope="module")
def demo_head():
    mesh = data.demo_head()
    return mesh.vertices, mesh.triangles()


@pytest.fixture(scope="module")
def demo_face(demo_head):
    return face_finding.find_face(*demo_head)


def test_demo_head_face_upright(demo_head, demo_face):
    vertices, triangles = demo_head           # the demo head: +Y up, +Z forward
    found = demo_face
    assert _angle(found.forward, (0, 0, 1)) < ANGLE_TOLERANCE
    assert _angle(found.up, (0, 1, 0)) < ANGLE_TOLERANCE
    assert _angle(found.right, (1, 0, 0)) < ANGLE_TOLERANCE      # the character's left
    assert np.allclose(found.frame.T @ found.frame, np.eye(3))
    assert found.presence > face_finding.MIN_PRESENCE and found.detection > face_finding.MIN_REDETECTION
    assert found.hits.sum() > 0.9 * len(found.points)
    assert np.array_equal(np.isnan(found.points[:, 0]), ~found.hits)
    tip = _nose_tip(vertices, np.arange(len(vertices)), found, np.array([0.0, 0.0, 1.0]))
    assert np.linalg.norm(found.landmarks()["nose_tip"] - tip) < NOSE_TOLERANCE * found.eye_distance


@pytest.mark.parametrize("seed, scale", [(1, 0.01), (7, 100.0)])
def test_frame_follows_any_rotation_and_scale(demo_head, demo_face, seed, scale):
    vertices, triangles = demo_head
    rotation = Rotation.random(random_state=seed).as_matrix()
    moved = scale * vertices @ rotation.T + np.array([3.0, -2.0, 5.0]) * scale
    found = face_finding.find_face(moved, triangles)
    assert _angle(found.forward, rotation @ demo_face.forward) < ANGLE_TOLERANCE
    assert _angle(found.up, rotation @ demo_face.up) < ANGLE_TOLERANCE
    assert found.eye_distance == pytest.approx(scale * demo_face.eye_distance, rel=0.1)
    # the same points on the same face, wherever it is turned
    back = (found.points / scale - np.array([3.0, -2.0, 5.0])) @ rotation
    both = found.hits & demo_face.hits
    assert both.sum() > 0.9 * len(both)
    spread = np.linalg.norm(back[both] - demo_face.points[both], axis=1)
    assert np.median(spread) < 0.05 * demo_face.eye_distance


def test_no_face_says_what_to_do():
    sphere_v = np.array([[0, 0, 1], [0, 0, -1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]], float)
    sphere_t = np.array([[0, 2, 4], [0, 4, 3], [0, 3, 5], [0, 5, 2],
                         [1, 4, 2], [1, 3, 4], [1, 5, 3], [1, 2, 5]])
    with pytest.raises(ExCloneError, match="select the head object.*apply.*landmarks"):
        face_finding.find_face(sphere_v, sphere_t)
    with pytest.raises(ExCloneError, match="select the head object"):
        face_finding.find_face(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))


@pytest.fixture(scope="module")
def library():
    return load_library()


@pytest.mark.parametrize("identity", [None, 5])
def test_ict_faces(library, shared_data, identity):
    """The ICT library's own face (one mesh with eyeballs, teeth, lashes inside it) and a new
    ICT identity: the face, its frame, and FaceMesh points at the library's landmarks."""
    from blender_tests.helpers.takes import identity_head
    vertices = identity_head(identity)[0]
    triangles = library.mesh.triangles()
    found = face_finding.find_face(vertices, triangles)
    assert _angle(found.forward, (0, 0, 1)) < ANGLE_TOLERANCE
    assert _angle(found.up, (0, 1, 0)) < ANGLE_TOLERANCE
    face_ids = np.arange(*library.parts["face"])
    on_face = np.isin(triangles[found.triangle[found.hits], 0], face_ids)
    assert on_face.mean() > 0.8
    tip = _nose_tip(vertices, face_ids, found, np.array([0.0, 0.0, 1.0]))
    assert np.linalg.norm(found.landmarks()["nose_tip"] - tip) < NOSE_TOLERANCE * found.eye_distance
    # the named FaceMesh points coincide with the library's landmarks (same vertex ids on every
    # ICT identity)
    names, ids = library.automatic_landmarks
    marks = found.landmarks()
    errors = {name: np.linalg.norm(marks[name] - vertices[i]) / found.eye_distance
              for name, i in zip(names, ids) if name in marks}
    assert set(errors) == set(face_finding.FACEMESH_LANDMARKS)
    assert np.mean(list(errors.values())) < 0.1
    assert max(errors.values()) < 0.25, errors


@pytest.mark.parametrize("turn_deg", [0.0, 180.0])
def test_an_open_mask_is_found_from_the_front(library, turn_deg):
    """The library's face region alone (an open surface, as a scan often is), facing +Z and turned
    to face -Z: its hollow inside, seen from behind, looks like a face to the models (left and
    right swapped); the face must be found from the front. Before the mirror check both were
    found from behind (forward at 175 degrees from the truth) and the clone's right eye did not
    close (96% of its opening left)."""
    from blender_tests.helpers.ground_truth import face_region
    neutral, triangles = face_region(library.mesh.vertices, library.mesh.loop_totals,
                                     library.mesh.loop_vertices)
    turn = Rotation.from_euler("y", turn_deg, degrees=True)
    found = face_finding.find_face(turn.apply(neutral), triangles)
    assert _angle(found.forward, turn.apply([0.0, 0.0, 1.0])) < ANGLE_TOLERANCE
    assert _angle(found.up, (0, 1, 0)) < ANGLE_TOLERANCE
    assert _angle(found.right, turn.apply([1.0, 0.0, 0.0])) < ANGLE_TOLERANCE


def test_head_region_keeps_the_skin_above_the_neck(library, shared_data):
    vertices, triangles = library.mesh.vertices, library.mesh.triangles()
    # a separate box under the head, as a body's other object would be
    box = np.array(np.meshgrid([-5, 5], [-60, -40], [-5, 5])).reshape(3, -1).T.astype(float)
    box_faces = np.array([[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6],
                          [0, 2, 6, 4], [1, 5, 7, 3]]) + len(vertices)
    box_triangles = PolyMesh.from_faces(np.vstack([vertices, box]), box_faces).triangles()
    all_vertices = np.vstack([vertices, box])
    all_triangles = np.vstack([triangles, box_triangles])
    found = face_finding.find_face(all_vertices, all_triangles)
    region = face_finding.head_region(all_vertices, all_triangles, found)
    assert region.shape == (len(all_vertices),)
    assert not region[len(vertices):].any()                       # not the other object
    parts = library.parts
    inside = {name: region[slice(*span)].mean() for name, span in parts.items()}
    assert inside["face"] > 0.95
    for name in ("eyeballs", "teeth", "gums_and_tongue", "eyelashes"):
        assert inside[name] == 0.0, name                            # few hits: not the skin
    # nothing below the cut plane; the cut is the rule's distance below the chin
    chin = np.nanmin(found.points @ found.up)          # the face's lowest point (152)
    height = (vertices @ found.up - chin) / found.face_height
    assert np.all(height[region[:len(vertices)]] >= -face_finding.HEAD_CUT_BELOW_CHIN)
    # the skin (the face's connected part) above the cut is all in
    labels = vertex_parts(len(vertices), triangles)
    skin = np.flatnonzero(labels == labels[parts["face"][0]])
    assert region[skin[height[skin] > -face_finding.HEAD_CUT_BELOW_CHIN + 0.05]].mean() > 0.99
