"""Automatic landmarks: the same in any supported orientation, absent where they do not exist,
a clear error on a mesh that is not a face, and close to hand-checked positions.

Meshes: the bundled library head (ICT-FaceKit) and the bundled demo head (MakeHuman); both are
in the repo, and the hand-checked fixtures (blender_tests/fixtures/) were made on the same files.
"""
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from blender_tests.helpers.paths import FIXTURES, SHARED_DATA
from blender_tests.helpers import ground_truth as gt
from exclone_addon.core import data
from exclone_addon.core.errors import ExCloneError
from exclone_addon.core.landmarks import HEURISTIC, NAMES, automatic_landmarks
from exclone_addon.core.library import load_library
from exclone_addon.core.mesh import read_obj
from exclone_addon.core.orientation import FaceFrame, face_frame
from exclone_addon.core.registration import similarity_transform

DEMO_HEAD = data.DEMO_HEAD_FILE

# Well-defined points a rotated copy must find again. Tolerance: 1% of the bounding-box diagonal
# (four of the detector's 0.25% profile bins; about twice what two careful annotators disagree on
# for these points, fixtures: 0.4-0.7%) plus the longest edge at the upright landmark's vertex
# (snapping to the neighbouring vertex is no instability; edges there: 0.2-1.5% of the diagonal).
ROBUST = ("nose_tip", "nose_bridge", "subnasal", "upper_lip", "lower_lip", "eye_inner_left",
          "eye_inner_right", "eye_outer_left", "eye_outer_right", "mouth_corner_left",
          "mouth_corner_right")
ORIENTATION_TOLERANCE = 0.01
FRONT_VIEW = Rotation.from_euler("x", 90, degrees=True).as_matrix()   # +Y up -> +Z up, -Y forward
# (base orientation, tilt in degrees about a random axis, seed of axis / scale / translation)
ORIENTATIONS = {
    "front_view": ("front", 0.0, 0),
    "y_up_tilt30": ("y_up", 30.0, 1),
    "front_view_tilt30": ("front", 30.0, 2),
    "y_up_tilt20": ("y_up", 20.0, 3),
    "front_view_tilt10": ("front", 10.0, 4),
}
FIXTURE_TOLERANCE = 0.02
HEADS = {"library": "ict_landmarks.json", "demo": "makehuman_landmarks.json"}


@pytest.fixture(scope="module")
def heads():
    lib = load_library()
    demo = read_obj(DEMO_HEAD)
    return {"library": (np.asarray(lib.mesh.vertices, dtype=np.float64), lib.mesh.triangles()),
            "demo": (np.asarray(demo.vertices, dtype=np.float64), demo.triangles())}


@pytest.fixture(scope="module")
def upright(heads):
    """Automatic landmarks of each head as shipped (+Y up, +Z forward): {name: vertex id}."""
    return {key: dict(zip(*automatic_landmarks(*heads[key]))) for key in heads}


def moved(vertices, base, angle, seed):
    """The head in `base` orientation, tilted by `angle` degrees about a random axis, scaled, moved."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    tilt = Rotation.from_rotvec(np.radians(angle) * axis / np.linalg.norm(axis)).as_matrix()
    rotation = tilt @ (FRONT_VIEW if base == "front" else np.eye(3))
    diagonal = np.linalg.norm(np.ptp(vertices, axis=0))
    scale = float(np.exp(rng.uniform(np.log(0.5), np.log(2.0))))
    return gt.apply_similarity(vertices, rotation, scale, rng.uniform(-diagonal, diagonal, 3))


@pytest.mark.parametrize("head,orientation", [
    pytest.param(head, orientation, id=f"{head}-{orientation}")
    for head in HEADS for orientation in ORIENTATIONS])
def test_same_landmarks_in_any_supported_orientation(heads, upright, head, orientation):
    vertices, triangles = heads[head]
    names, ids = automatic_landmarks(moved(vertices, *ORIENTATIONS[orientation]), triangles)
    found = dict(zip(names, ids))
    reference = upright[head]
    diagonal = np.linalg.norm(np.ptp(vertices, axis=0))
    edges = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    edge_length = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1) / diagonal
    longest_edge = np.zeros(len(vertices))
    np.maximum.at(longest_edge, edges.ravel(), np.repeat(edge_length, 2))
    lines, wrong = [], []
    for name in NAMES:
        if name not in reference:
            continue
        if name not in found:
            error = np.inf
        else:
            error = np.linalg.norm(vertices[found[name]] - vertices[reference[name]]) / diagonal
        lines.append(f"{name} {100 * error:.2f}%")
        tolerance = ORIENTATION_TOLERANCE + longest_edge[reference[name]]
        if name in ROBUST and error > tolerance:
            wrong.append(f"{name} {100 * error:.2f}% (tolerance {100 * tolerance:.2f}%)")
    print(f"\n[{head} {orientation}] moved landmark vs upright, % of diagonal: " + ", ".join(lines))
    assert set(found) == set(reference), (
        f"landmarks found upright but not here: {sorted(set(reference) - set(found))}; "
        f"here but not upright: {sorted(set(found) - set(reference))}")
    assert not wrong, f"robust landmarks moved: {wrong}"


def test_robust_landmarks_exist_on_both_heads(upright):
    for head, found in upright.items():
        missing = [n for n in ROBUST if n not in found]
        assert not missing, f"{head}: no {missing}"


IDENTITIES = SHARED_DATA / "ict-facekit" / "identities.npz"


@pytest.mark.skipif(not IDENTITIES.exists(),
                    reason=f"needs the shared ICT identity model ({IDENTITIES})")
def test_nose_tip_on_a_face_whose_lower_lip_reaches_further_forward():
    """ICT identity 6's face region (weights drawn as test_unseen_identity draws them), tilted,
    scaled and moved: in its own frame its lower lip stands in front of its nose tip. The nose
    tip is found on the nose (the uppermost of the midline's strong bumps), and the other points
    from it, near where the library's face region has them (before, as the front-most midline
    vertex: the tip on the lower lip, and from there too few points found here; in
    test_unseen_identity's remeshed copy of this face 20 points, 11-35% of the diagonal off)."""
    lib = load_library()
    with np.load(IDENTITIES) as model:
        modes = model["deltas"].astype(np.float64)
    face = lib.mesh.vertices + np.tensordot(np.random.default_rng(6).standard_normal(len(modes)),
                                            modes, 1)
    polygons = (lib.mesh.loop_totals, lib.mesh.loop_vertices)
    truth = dict(zip(*automatic_landmarks(*gt.face_region(lib.mesh.vertices, *polygons))))
    region, triangles = gt.face_region(face, *polygons)
    vertices = moved(region, "front", 20.0, 6)
    frame = face_frame(vertices, triangles)
    forward = frame.to_canonical(vertices[[truth["lower_lip"], truth["nose_tip"]]])[:, 2]
    assert forward[0] > forward[1]                # the face it is about
    found = dict(zip(*automatic_landmarks(vertices, triangles, frame)))
    for name in ROBUST:
        error = np.linalg.norm(vertices[found[name]] - vertices[truth[name]]) / frame.diagonal
        assert error < 0.03, f"{name} {100 * error:.1f}% of the diagonal from the identity's own"


# Whole ICT identity heads (the library's mesh, eyes, mouth interior and neck, with an
# identity's deltas): the frame's forward should be the library head's (the identities share its
# pose to 2-3 degrees) within what their face regions reach (1-8 degrees), and the nose tip the
# library's tip vertex (x the diagonal).
WHOLE_HEAD_FORWARD_BAR, WHOLE_HEAD_TIP_BAR = 5.0, 0.02


@pytest.mark.skipif(not IDENTITIES.exists(),
                    reason=f"needs the shared ICT identity model ({IDENTITIES})")
@pytest.mark.xfail(strict=True, reason=(
    "measured: forward 18.4 / 22.9 degrees off, the nose tip on the lower lip 10.3% / 9.3% of "
    "the diagonal off (seeds 6 / 9): docs/method.md §3's refinement (the mean normal within a "
    "quarter of the diagonal of the tip) takes in the mouth socket, the chin's underside and the "
    "neck, and the tip's surroundings (§4) the mouth socket behind the lips"))
@pytest.mark.parametrize("seed", [6, 9])
def test_frame_and_nose_tip_on_a_whole_identity_head(seed):
    """A whole ICT identity head (weights drawn as test_unseen_identity draws them), tilted,
    scaled and moved: its frame's forward is the library head's frame's (moved alike), its nose
    tip the library's nose tip vertex."""
    lib = load_library()
    with np.load(IDENTITIES) as model:
        modes = model["deltas"].astype(np.float64)
    head = lib.mesh.vertices + np.tensordot(
        np.random.default_rng(seed).standard_normal(len(modes)), modes, 1)
    triangles = lib.mesh.triangles()
    library = face_frame(lib.mesh.vertices, triangles)
    vertices = moved(head, "front", 20.0, seed)
    turn = similarity_transform(head, vertices)[0]
    frame = face_frame(vertices, triangles)
    off = np.degrees(np.arccos(np.clip(frame.rotation[:, 2] @ turn @ library.rotation[:, 2],
                                       -1, 1)))
    found = dict(zip(*automatic_landmarks(vertices, triangles, frame)))
    tip = dict(zip(*automatic_landmarks(lib.mesh.vertices, triangles, library)))["nose_tip"]
    error = np.linalg.norm(vertices[found["nose_tip"]] - vertices[tip]) / frame.diagonal
    print(f"\n[seed {seed}] forward {off:.1f} degrees off, nose tip {100 * error:.1f}% of the "
          "diagonal off")
    assert off < WHOLE_HEAD_FORWARD_BAR, f"forward {off:.1f} degrees off"
    assert error < WHOLE_HEAD_TIP_BAR, f"nose tip {100 * error:.1f}% of the diagonal off"


def test_face_mask_has_no_head_landmarks():
    """The ICT face region alone (vertices 0-9408): a mask, open behind."""
    lib = load_library()
    vertices, triangles = gt.face_region(lib.mesh.vertices, lib.mesh.loop_totals,
                                         lib.mesh.loop_vertices)
    names, ids = automatic_landmarks(vertices, triangles)
    assert not {"head_back", "head_top", "ear_tip_left", "ear_tip_right"} & set(names), names
    for name in ROBUST:
        assert name in names, f"the face mask lost {name}"
    assert len(set(ids.tolist())) == len(ids)


def uv_sphere(radius_of, rings=40, segments=60):
    """A closed UV sphere whose radius at each unit direction is radius_of(directions)."""
    theta = np.linspace(0, np.pi, rings + 1)[1:-1]
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    d = np.stack([np.sin(t) * np.cos(p), np.cos(t), np.sin(t) * np.sin(p)], -1).reshape(-1, 3)
    d = np.vstack([d, [[0, 1, 0], [0, -1, 0]]])
    vertices = d * radius_of(d)[:, None]
    top, bottom = len(d) - 2, len(d) - 1
    tris = []
    for i in range(rings - 2):
        for j in range(segments):
            a, b = i * segments + j, i * segments + (j + 1) % segments
            c, e = a + segments, b + segments
            tris += [[a, c, b], [b, c, e]]
    for j in range(segments):
        tris.append([top, j, (j + 1) % segments])
        last = (rings - 2) * segments
        tris.append([bottom, last + (j + 1) % segments, last + j])
    return vertices, np.array(tris)


def blob(amplitude=0.1):
    """A sphere with random smooth bumps (radius 1 +- about 3 x amplitude)."""
    rng = np.random.default_rng(0)
    lobes = rng.normal(size=(6, 3))
    phases = rng.normal(size=6)
    return uv_sphere(lambda d: 1.0 + amplitude * np.sin(2.0 * d @ lobes.T + phases).sum(axis=1))


def mild_blob():
    return blob(amplitude=0.03)


def flat_plane():
    x, y = np.meshgrid(np.linspace(-1, 1, 30), np.linspace(-1, 1, 30))
    vertices = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    k = np.arange(29)[:, None] * 30 + np.arange(29)[None, :]
    k = k.ravel()
    tris = np.concatenate([np.stack([k, k + 1, k + 31], 1), np.stack([k, k + 31, k + 30], 1)])
    return vertices, tris


def sphere():
    return uv_sphere(lambda d: np.ones(len(d)))


@pytest.mark.parametrize("shape", [blob, mild_blob, flat_plane, sphere])
def test_not_a_face_asks_for_manual_landmarks(shape):
    vertices, triangles = shape()
    with pytest.raises(ExCloneError) as error:
        automatic_landmarks(vertices, triangles)
    message = str(error.value)
    assert "\n" not in message
    assert "landmarks" in message and ("by hand" in message or "manual" in message), message


# Meshes in the canonical frame itself (identity rotation), so the heuristics see them as given:
# nothing near the midline (two plates beside it), and a head-deep midline with no skull above
# the nose.
def plates_beside_the_midline():
    square = np.array([[1, -1, 0], [2, -1, 0], [2, 1, 0], [1, 1, 0]], dtype=float)
    vertices = np.vstack([square, square * [-1, 1, 1]])
    return vertices, np.array([[0, 1, 2], [0, 2, 3], [4, 6, 5], [4, 7, 6]])


def midline_without_skull():
    vertices = np.array([[0, 0, 1], [0, 0, -1], [0, -2, 0], [1, 1, 0], [-1, 1, 0]], dtype=float)
    return vertices, np.array([[0, 1, 2], [0, 3, 1], [0, 1, 4]])


@pytest.mark.parametrize("shape,what", [(plates_beside_the_midline, "nose tip"),
                                        (midline_without_skull, "skull")])
def test_an_empty_section_asks_for_manual_landmarks(shape, what):
    vertices, triangles = shape()
    frame = FaceFrame(np.eye(3), np.zeros(3), float(np.linalg.norm(np.ptp(vertices, axis=0))), 0.0)
    with pytest.raises(ExCloneError, match=f"could not find the face's {what}.*place the "
                                           "landmarks by hand"):
        automatic_landmarks(vertices, triangles, frame)


def fixture_tolerance(fixture, name):
    """2% of the diagonal, or the fixture's annotator-disagreement estimate where it calls the
    landmark ambiguous and that is larger."""
    if name in fixture["uncertain"]:
        return max(FIXTURE_TOLERANCE, fixture["disagreement_estimate_pct_of_diagonal"][name] / 100)
    return FIXTURE_TOLERANCE


def fixture_names(head):
    """Landmarks checked against the fixture. Excluded: on the library head, the landmarks the
    template places (mouth_corner_*, brow_*, jaw_*): the template IS this mesh, those points
    are its own iBUG vertices, so the check would be circular. The eye's outer corners and upper
    lids are found by heuristics on it."""
    if head == "library":
        return list(HEURISTIC) + ["eye_outer_left", "eye_outer_right", "eyelid_upper_left",
                                  "eyelid_upper_right"]
    return list(NAMES)


@pytest.fixture(scope="module")
def fixtures():
    return {head: json.loads((FIXTURES / name).read_text()) for head, name in HEADS.items()}


@pytest.fixture(scope="module")
def fixture_errors(heads, upright, fixtures):
    """{head: {name: error as a fraction of the fixture's bbox_diagonal}}, printed as a table."""
    errors = {}
    for head in HEADS:
        vertices, _ = heads[head]
        fixture = fixtures[head]
        assert len(vertices) == fixture["vertex_count"]
        errors[head] = {}
        for name in fixture_names(head):
            if name in upright[head]:
                position = np.asarray(fixture["landmarks"][name]["position"])
                errors[head][name] = (np.linalg.norm(vertices[upright[head][name]] - position)
                                      / fixture["bbox_diagonal"])
            else:
                errors[head][name] = np.inf
    print("\nautomatic vs hand-checked landmarks, % of bbox diagonal (tolerance):")
    for head in HEADS:
        for name, error in errors[head].items():
            print(f"  {head:8s} {name:20s} {100 * error:6.2f}  "
                  f"({100 * fixture_tolerance(fixtures[head], name):.1f})")
    return errors


@pytest.mark.parametrize("head,name", [pytest.param(head, name, id=f"{head}-{name}")
                                       for head in HEADS for name in fixture_names(head)])
def test_automatic_landmark_near_hand_checked(fixtures, fixture_errors, head, name):
    tolerance = fixture_tolerance(fixtures[head], name)
    error = fixture_errors[head][name]
    assert error <= tolerance, (f"{head} {name}: {100 * error:.2f}% of the diagonal from the "
                                f"hand-checked vertex (tolerance {100 * tolerance:.1f}%)")


def test_shipped_landmark_template_is_current():
    # the template file is derived data: stale after a heuristic or library change
    from exclone_addon.core.data import LANDMARK_TEMPLATE_FILE
    from exclone_addon.core.landmark_template import compute_template
    shipped = json.loads(LANDMARK_TEMPLATE_FILE.read_text())
    fresh, normals, (names, ids) = compute_template()
    positions = shipped["canonical_positions"]
    assert set(positions) == set(fresh), "run scripts/make_landmark_template.py"
    for name, position in fresh.items():
        assert np.allclose(positions[name], position, atol=1e-6), (
            f"{name} changed: run scripts/make_landmark_template.py")
    assert set(shipped["canonical_normals"]) == set(normals), "run scripts/make_landmark_template.py"
    for name, normal in normals.items():
        assert np.allclose(shipped["canonical_normals"][name], normal, atol=1e-6), (
            f"{name}'s normal changed: run scripts/make_landmark_template.py")
    assert shipped["library_landmarks"] == dict(zip(names, ids.tolist())), (
        "the library's landmarks changed: run scripts/make_landmark_template.py")
