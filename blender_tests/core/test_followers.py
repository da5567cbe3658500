"""Parts that follow the face (core/followers.py): an eyeball part inside the target mesh stays
still except in its eyeLook keys, where it turns about its centre by the stated angle; the rules'
pieces (sphere fit, gaze rotations, the jaw's rigid fit, the mouth's roles) on known shapes."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from exclone_addon.core import data, followers
from exclone_addon.core.cloning import clone_expressions, found_landmarks
from exclone_addon.core.library import load_library
from exclone_addon.core.mesh import PolyMesh

NAMES = ["eyeLookIn_L", "eyeLookOut_L", "eyeLookUp_L", "eyeLookIn_R", "eyeBlink_L", "jawOpen"]


def sphere(centre, radius, rings=10, segments=16):
    """A closed UV sphere as (vertices, quads and triangle fans)."""
    theta = np.linspace(0, np.pi, rings + 1)[1:-1]
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    ring = np.stack([np.outer(np.sin(theta), np.cos(phi)), np.outer(np.cos(theta), np.ones_like(phi)),
                     np.outer(np.sin(theta), np.sin(phi))], axis=-1).reshape(-1, 3)
    points = np.vstack([[[0, 1, 0]], ring, [[0, -1, 0]]]) * radius + centre
    at = lambda r, s: 1 + r * segments + s % segments  # noqa: E731
    faces = [[0, at(0, s + 1), at(0, s)] for s in range(segments)]
    faces += [[at(r, s), at(r, s + 1), at(r + 1, s + 1), at(r + 1, s)]
              for r in range(rings - 2) for s in range(segments)]
    faces += [[at(rings - 2, s), at(rings - 2, s + 1), len(points) - 1] for s in range(segments)]
    return points, faces


@pytest.fixture(scope="module")
def head_with_eyes():
    """The demo head (file axes: +Y up, +Z forward, +X the character's left) with an eyeball
    part behind each eye's corners, cloned with the library."""
    head = data.demo_head()
    library = load_library()
    marks = dict(zip(*found_landmarks(head)))
    meshes = [head]
    eyes = []
    for side in ("left", "right"):
        inner, outer = head.vertices[marks[f"eye_inner_{side}"]], head.vertices[marks[f"eye_outer_{side}"]]
        radius = 0.45 * np.linalg.norm(outer - inner)
        points, faces = sphere((inner + outer) / 2 - [0, 0, 0.8 * radius], radius)
        eyes.append(np.arange(len(points)) + sum(len(m.vertices) for m in meshes))
        meshes.append(PolyMesh.from_faces(points, faces))
    target = PolyMesh(np.vstack([m.vertices for m in meshes]),
                      np.concatenate([m.loop_totals for m in meshes]),
                      np.concatenate([m.loop_vertices + sum(len(k.vertices) for k in meshes[:i])
                                      for i, m in enumerate(meshes)]))
    sub = library.subset(NAMES)
    result = clone_expressions(sub.mesh, sub.deltas, sub.names, target,
                               source_landmarks=library.automatic_landmarks)
    return target, eyes, dict(zip(result.names, result.deltas)), marks


def turn_about(rest, moved):
    """(rotation, centre motion) of a rigid motion of points."""
    rotation = Rotation.align_vectors(moved - moved.mean(axis=0), rest - rest.mean(axis=0))[0]
    return rotation, moved.mean(axis=0) - rest.mean(axis=0)


def test_eye_parts_stay_still_but_look_by_the_stated_angle(head_with_eyes):
    target, eyes, deltas, marks = head_with_eyes
    size = np.ptp(target.vertices, axis=0).max()
    for name in ("eyeBlink_L", "jawOpen"):
        for eye in eyes:
            assert np.abs(deltas[name][eye]).max() <= 1e-9, name
    left, right = eyes
    # the right eye does not move in the left eye's keys, and the other way round
    assert np.abs(deltas["eyeLookIn_L"][right]).max() <= 1e-9
    assert np.abs(deltas["eyeLookIn_R"][left]).max() <= 1e-9
    rest = target.vertices[left]
    rotation, shift = turn_about(rest, rest + deltas["eyeLookIn_L"][left])
    angle = np.degrees(rotation.magnitude())
    print(f"eyeLookIn_L turns the left eye by {angle:.2f} degrees")
    assert abs(angle - followers.EYE_LOOK_DEGREES["In"]) < 1
    assert np.linalg.norm(shift) < 1e-3 * size          # about its own centre (nearly)
    gaze = rotation.apply([0, 0, 1.0])                  # the file's forward is +Z, left is +X
    assert gaze[0] < -0.4                               # towards the nose: to the right
    gaze = turn_about(rest, rest + deltas["eyeLookOut_L"][left])[0].apply([0, 0, 1.0])
    assert gaze[0] > 0.4
    rotation = turn_about(rest, rest + deltas["eyeLookUp_L"][left])[0]
    assert abs(np.degrees(rotation.magnitude()) - followers.EYE_LOOK_DEGREES["Up"]) < 1
    assert rotation.apply([0, 0, 1.0])[1] > 0.3        # up
    gaze = turn_about(target.vertices[right], target.vertices[right]
                      + deltas["eyeLookIn_R"][right])[0].apply([0, 0, 1.0])
    assert gaze[0] > 0.4                                # the right eye's nose is to its left


def test_fitted_sphere_is_exact_on_a_sphere():
    points, _ = sphere(np.array([1.0, -2.0, 0.5]), 0.3)
    centre, radius = followers._fitted_sphere(points)
    assert np.allclose(centre, [1.0, -2.0, 0.5]) and np.isclose(radius, 0.3)


def test_jaw_motion_is_rigid_and_needs_a_rigid_patch():
    rng = np.random.default_rng(1)
    face = followers.Face(None, np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0]),
                          np.zeros(3), np.array([0, -3.0, 0]), np.zeros((2, 3)), 9.0)
    joint = face.mouth + face.span * (followers.JAW_JOINT[0] * face.up
                                      - followers.JAW_JOINT[1] * face.forward)
    rest = rng.normal(size=(40, 3)) + [0, -3, 0]
    points = rng.normal(size=(30, 3)) + [0, -2, -2]
    # a turn about the jaw's joint (mostly about the face's left axis) is carried exactly
    turn = Rotation.from_rotvec([0.3, 0.05, 0])
    about_joint = lambda x: turn.apply(x - joint) + joint  # noqa: E731
    motion = followers._jaw_motion(face, rest, about_joint(rest) - rest, points)
    assert np.allclose(points + motion, about_joint(points))
    sliding = rng.normal(size=rest.shape) * 0.1          # skin that slides, no bone under it
    assert not followers._jaw_motion(face, rest, sliding, points).any()


def test_eye_look_names_with_and_without_a_prefix():
    assert followers.eye_look("eyeLookIn_L") == (0, "In")
    assert followers.eye_look("lib_eyeLookDown_R") == (1, "Down")
    assert followers.eye_look("eyeBlink_L") is None and followers.eye_look("eyeLookIn") is None
