"""core.eyes and face_models.IrisLandmarker on a real photograph (skimage's astronaut, public
domain) and on known geometry: where the iris model puts the pupils and eye corners, readings
that do not change as the face moves, the eyes' rows of the weight solve."""
import cv2
import numpy as np
import pytest
from skimage import data

from exclone_addon.core import eyes
from exclone_addon.core.face_models import (EyeLandmarks, FaceDetector, FaceLandmarker,
                                            IrisLandmarker, roi_from_detection,
                                            roi_from_landmarks)
from exclone_addon.core.retarget import WeightSolver
from blender_tests.core.test_face_models import HAND_POINTS, HAND_PUPILS


@pytest.fixture(scope="module")
def astronaut_eyes():
    """(image, FaceMesh points, EyeLandmarks) of the astronaut, and of her mirror image."""
    detector, landmarker, iris = FaceDetector(), FaceLandmarker(), IrisLandmarker()
    found = []
    image = cv2.cvtColor(data.astronaut(), cv2.COLOR_RGB2BGR)
    for picture in (image, np.ascontiguousarray(image[:, ::-1])):
        points, _ = landmarker.landmarks(picture, roi_from_detection(detector.detect(picture)[0]))
        points, _ = landmarker.landmarks(picture, roi_from_landmarks(points))
        found.append((picture, points, iris.eyes(picture, points)))
    return found


def test_iris_centres_on_the_hand_measured_pupils_and_corners(astronaut_eyes):
    _, _, eye_points = astronaut_eyes[0]
    for k in range(2):
        assert np.linalg.norm(eye_points.irises[k, 0] - HAND_PUPILS[k]) < 2.5
    # contour 0 is the outer corner of each eye, 8 the inner one (iBUG 36, 39, 42, 45)
    corners = {36: eye_points.contours[0, 0], 39: eye_points.contours[0, 8],
               42: eye_points.contours[1, 8], 45: eye_points.contours[1, 0]}
    for ibug, point in corners.items():
        assert np.linalg.norm(point - HAND_POINTS[ibug]) < 4.0, ibug


def test_the_mirrored_face_reads_the_same_with_the_eyes_swapped(astronaut_eyes):
    """The image-right eye is mirrored before the model: a mirrored photograph gives each eye
    the crop the other eye had, so the readings swap (gaze x changes sign)."""
    (_, _, plain), (_, _, mirrored) = astronaut_eyes
    a, b = eyes.read_eyes(plain), eyes.read_eyes(mirrored)
    np.testing.assert_allclose(a.upper, b.upper[::-1], atol=0.02)
    np.testing.assert_allclose(a.lower, b.lower[::-1], atol=0.02)
    np.testing.assert_allclose(a.iris[:, 0], -b.iris[::-1, 0], atol=0.02)
    np.testing.assert_allclose(a.iris[:, 1], b.iris[::-1, 1], atol=0.02)
    assert np.all(a.opening > 0.15), "the astronaut's eyes are open"


def test_reading_does_not_change_as_the_face_moves_nearer_or_rolls(astronaut_eyes):
    _, _, eye_points = astronaut_eyes[0]
    reading = eyes.read_eyes(eye_points)
    angle = np.radians(25)
    turn = 1.7 * np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    moved = EyeLandmarks(contours=eye_points.contours @ turn.T + (40, -30),
                         irises=eye_points.irises @ turn.T + (40, -30))
    again = eyes.read_eyes(moved)
    for name in ("upper", "lower", "iris"):
        np.testing.assert_allclose(getattr(again, name), getattr(reading, name), atol=1e-9)


ARKIT_EYES = [f"{key}{side}" for side in eyes.SIDES for key in
              ("eyeBlink", "eyeWide", "eyeSquint", "eyeLookUp", "eyeLookDown", "eyeLookIn", "eyeLookOut")]


def solve_eyes_only(reading, neutral, names=ARKIT_EYES):
    """The weights the eye rows alone ask for (landmark shapes that never move)."""
    solver = WeightSolver(np.zeros((len(names), 10, 3)), names)
    targets = eyes.EyeTargets(names, neutral, key_scale=1.0)
    rows, values = targets.rows(reading)
    return dict(zip(names, solver.solve(np.zeros((10, 3)), rows, values))), targets


NEUTRAL = eyes.EyeReading(upper=np.array([0.2, 0.2]), lower=np.array([-0.12, -0.12]),
                          iris=np.zeros((2, 2)))


def test_rows_read_a_closed_eye_as_a_blink_and_hold_the_gaze():
    opening = NEUTRAL.opening
    looking = eyes.EyeReading(NEUTRAL.upper.copy(), NEUTRAL.lower.copy(), np.zeros((2, 2)))
    looking.iris[:, 0] = eyes.EYE_RADIUS_WIDTHS * np.sin(np.radians(15))   # 15 deg to the left
    weights, targets = solve_eyes_only(looking, NEUTRAL)
    assert weights["eyeLookOut_L"] == pytest.approx(0.5, abs=0.02)
    assert weights["eyeLookIn_R"] == pytest.approx(0.5, abs=0.02)
    assert weights["eyeBlink_L"] < 0.05 and weights["eyeLookDown_L"] < 0.05
    # closed: the upper lid down by 0.45 of the opening, the iris read far down (as the model
    # guesses a hidden iris); the gaze holds the open eyes' 15 degrees
    closed = eyes.EyeReading(NEUTRAL.upper - 0.45 * opening, NEUTRAL.lower + 0.1 * opening,
                             looking.iris + [0.0, -0.2])
    rows, values = targets.rows(closed)
    solver = WeightSolver(np.zeros((len(ARKIT_EYES), 10, 3)), ARKIT_EYES)
    weights = dict(zip(ARKIT_EYES, solver.solve(np.zeros((10, 3)), rows, values)))
    for side in eyes.SIDES:
        assert weights["eyeBlink" + side] > 0.9
        assert weights["eyeLookDown" + side] < 0.05
    assert weights["eyeLookOut_L"] == pytest.approx(0.5, abs=0.05)


def test_an_avatar_without_arkit_eye_keys_gets_no_eye_rows():
    targets = eyes.EyeTargets(["jawOpen", "smile"], NEUTRAL, key_scale=1.0)
    assert targets.rows(NEUTRAL) == (None, None)
    weights, _ = solve_eyes_only(NEUTRAL, NEUTRAL, names=["eyeBlink_L", "jawOpen"])
    assert weights["eyeBlink_L"] < 1e-6


def test_keys_that_close_an_eye_are_its_blink_whatever_their_names():
    """An avatar with its own keys (a character's eye-left-closure, VRM's Blink): the keys
    that close an eye on the avatar (retarget.eye_closures) get that eye's blink rows, the
    others none; a closed eye reads them closed, an open one open. An avatar with the ARKit lid
    keys keeps its rows by name whatever the closures say."""
    names = ["eye-right-closure", "eye-left-closure", "Blink", "squint_R", "mouth-open"]
    # the share of each eye's opening (subject's right, left) each key closes
    closures = np.array([[1.0, 0.0], [0.0, 0.95], [1.0, 1.0], [0.3, 0.0], [0.0, 0.0]])
    targets = eyes.EyeTargets(names, NEUTRAL, key_scale=1.0, closures=closures)
    assert targets.keys.tolist() == [True, True, True, False, False]
    opening = NEUTRAL.opening
    left_closed = eyes.EyeReading(NEUTRAL.upper - [0.0, 0.45 * opening[1]],
                                  NEUTRAL.lower + [0.0, 0.1 * opening[1]], NEUTRAL.iris.copy())
    solver = WeightSolver(np.zeros((len(names), 10, 3)), names)
    for reading, expected in ((NEUTRAL, [0, 0, 0]), (left_closed, [0, 1, 0])):
        rows, values = targets.rows(reading)
        weights = solver.solve(np.zeros((10, 3)), rows, values)
        # each closing key alone would explain its eye; together the solve shares it out
        assert weights[0] + weights[2] == pytest.approx(expected[0], abs=0.05)
        assert weights[1] * 0.95 + weights[2] == pytest.approx(expected[1], abs=0.05)
        assert weights[3] < 1e-6 and weights[4] < 1e-6
    arkit = ["eyeBlink_R", "eyeBlink_L", "eye-left-closure"]
    by_name = eyes.EyeTargets(arkit, NEUTRAL, key_scale=1.0)
    with_closures = eyes.EyeTargets(arkit, NEUTRAL, key_scale=1.0,
                                    closures=np.array([[1.0, 0.0], [0.0, 1.0], [0.0, 1.0]]))
    np.testing.assert_array_equal(by_name.rows(left_closed)[0], with_closures.rows(left_closed)[0])


def test_the_rows_name_the_keys_they_read():
    names = ["jawOpen", "eyeBlink_L", "eyeLookOut_R", "browDown_L", "eyeWide_R", "eyeSquint_L"]
    targets = eyes.EyeTargets(names, NEUTRAL, key_scale=1.0)
    assert targets.keys.tolist() == [False, True, True, False, True, True]
    assert not eyes.EyeTargets(["jawOpen", "smile"], NEUTRAL, key_scale=1.0).keys.any()


@pytest.mark.parametrize("turn", [(0, 0, 0), (30, 0, 0), (0, 20, 0), (-25, 15, 10)])
def test_geometry_brings_a_turned_heads_reading_back_to_frontal(turn):
    """Eyes with known lids and gaze seen on a head turned by `turn` (yxz degrees): the reading
    differs from the frontal one (the iris is in front of the corners), frontal() recovers it."""
    from scipy.spatial.transform import Rotation
    from exclone_addon.core import data
    from exclone_addon.core.tracking import FRONTAL, Camera
    shape = data.canonical_face().vertices
    geometry = eyes.EyeGeometry(shape, Camera.from_image_size(640, 480))
    rotation = Rotation.from_euler("yxz", turn, degrees=True) * FRONTAL
    translation = np.array([0.0, 0.0, 50.0]) - rotation.apply(shape.mean(axis=0))
    centres = np.array([[0.02, 0.01], [-0.02, 0.01]])
    gaze = np.array([0.08, -0.05])          # the iris's frontal shift, eye widths
    r = eyes.EYE_RADIUS_WIDTHS
    depth = eyes.IRIS_DEPTH_WIDTHS - r + r * np.sqrt(1.0 - (gaze ** 2).sum() / r ** 2)
    seen = np.array([geometry._reading_of(k, geometry._points(0.2, -0.1, [*(centres[k] + gaze), depth]),
                                          rotation, translation) for k in range(2)])
    reading = eyes.EyeReading(seen[:, 0], seen[:, 1], seen[:, 2:])
    frontal = geometry.frontal(reading, rotation, translation, centres)
    np.testing.assert_allclose(frontal.upper, 0.2, atol=1e-6)
    np.testing.assert_allclose(frontal.lower, -0.1, atol=1e-6)
    np.testing.assert_allclose(frontal.iris - centres, [gaze, gaze], atol=1e-6)
    if turn[0]:
        assert np.abs(reading.iris - centres - gaze).max() > 0.03


def test_the_learnt_slide_is_taken_off_the_frontal_reading():
    """A geometry with an EyeSlide reads frontal what one without it reads, less the slide at
    the pose; facing the camera the slide is nothing."""
    from scipy.spatial.transform import Rotation
    from exclone_addon.core import data
    from exclone_addon.core.tracking import FRONTAL, POSE_FEATURES, Camera
    shape = data.canonical_face().vertices
    camera = Camera.from_image_size(640, 480)
    offsets = np.random.default_rng(3).normal(0, 0.05, (len(POSE_FEATURES), 2, eyes.READING_MEASURES))
    slide = eyes.EyeSlide(offsets, shape.mean(axis=0))
    plain, slid = eyes.EyeGeometry(shape, camera), eyes.EyeGeometry(shape, camera, slide)
    reading = eyes.EyeReading(np.array([0.15, 0.16]), np.array([-0.1, -0.11]),
                              np.array([[0.01, 0.02], [-0.01, 0.02]]))
    centres = np.zeros((2, 2))
    for turn in ((0, 0, 0), (30, -15, 5)):
        rotation = Rotation.from_euler("yxz", turn, degrees=True) * FRONTAL
        translation = np.array([0.0, 0.0, 50.0]) - rotation.apply(shape.mean(axis=0))
        expected = eyes.reading_measures(plain.frontal(reading, rotation, translation, centres))
        if turn[0]:
            expected = expected - slide.at(rotation, translation)
            assert np.abs(slide.at(rotation, translation)).max() > 0.01
        else:
            np.testing.assert_allclose(slide.at(rotation, translation), 0.0, atol=1e-12)
        found = eyes.reading_measures(slid.frontal(reading, rotation, translation, centres))
        np.testing.assert_allclose(found, expected, atol=1e-12)


def test_a_pitched_heads_eyes_face_the_camera_less():
    """Pitched 20 degrees, both eyes are foreshortened along their lids alike (about the cosine
    of the pitch); their corner lines are not."""
    from scipy.spatial.transform import Rotation
    from exclone_addon.core import data
    from exclone_addon.core.tracking import FRONTAL, Camera
    geometry = eyes.EyeGeometry(data.canonical_face().vertices, Camera.from_image_size(640, 480))
    for pitch in (20, -20):
        facing = geometry.facing(Rotation.from_euler("x", pitch, degrees=True) * FRONTAL)
        np.testing.assert_allclose(facing, np.cos(np.radians(20)), atol=0.02)


def test_a_turned_eyes_lids_count_less():
    """A head turned 30 degrees: the far eye faces the camera less than the near one, both less
    than facing it, and the same lid change asks for less of the far eye's key."""
    from scipy.spatial.transform import Rotation
    from exclone_addon.core import data
    from exclone_addon.core.tracking import FRONTAL, Camera
    geometry = eyes.EyeGeometry(data.canonical_face().vertices, Camera.from_image_size(640, 480))
    np.testing.assert_allclose(geometry.facing(FRONTAL), 1.0)
    # turned so that the image-left eye (the subject's right, eye 0) is the far one
    facing = geometry.facing(Rotation.from_euler("y", 30, degrees=True) * FRONTAL)
    assert facing[0] < 0.9 and facing[0] < facing[1] <= 1.0, facing
    # both lower lids up by 0.15 of the opening: the ridge holds each squint back, the far eye's
    # less trusted reading further
    names = ["eyeSquint_R", "eyeSquint_L"]
    solver = WeightSolver(np.zeros((2, 10, 3)), names, ridge=1.0, scale=1.0)
    targets = eyes.EyeTargets(names, NEUTRAL, key_scale=1.0)
    squinting = eyes.EyeReading(NEUTRAL.upper, NEUTRAL.lower + 0.15 * NEUTRAL.opening,
                                NEUTRAL.iris, facing=facing)
    weights = solver.solve(np.zeros((10, 3)), *targets.rows(squinting))
    assert weights[0] < weights[1], weights


def test_a_turned_eyes_lower_lid_counts_less_than_its_upper_lid():
    """The iris model loses a turned eye's lower lid first: facing the camera, a wide and a
    squint of the same size are read alike; with the eye turned (facing 0.85) the squint, read
    from the lower lid, is held back far more than the wide, read from the upper."""
    names = ["eyeWide_R", "eyeSquint_R"]
    solver = WeightSolver(np.zeros((2, 10, 3)), names, ridge=1.0, scale=1.0)
    targets = eyes.EyeTargets(names, NEUTRAL, key_scale=1.0)
    changes = {key: (up, down) for key, up, down in eyes.LID_CHANGES}
    opening = NEUTRAL.opening
    read = {}
    for facing in (1.0, 0.85):
        # each lid moved as half of its key does
        reading = eyes.EyeReading(NEUTRAL.upper + 0.5 * changes["eyeWide"][0] * opening,
                                  NEUTRAL.lower + 0.5 * changes["eyeSquint"][1] * opening,
                                  NEUTRAL.iris, facing=np.full(2, facing))
        read[facing] = solver.solve(np.zeros((10, 3)), *targets.rows(reading))
    wide, squint = read[1.0]
    assert squint > 0.8 * wide > 0.2, read
    wide, squint = read[0.85]
    assert squint < 0.2 * wide, read


def test_an_eye_does_not_look_in_and_out_at_once():
    """A character's cloned eyeLookIn and eyeLookOut move the face's points about alike and
    opposite (their sum by a fifth of either): the points' motion along that sum, with the eyes
    looking ahead, must not raise both keys (the yaw row alone does not see their sum)."""
    rng = np.random.default_rng(0)
    names = ["eyeLookIn_R", "eyeLookOut_R", "browOuterUp_R"]
    look = rng.normal(size=(10, 3))
    shapes = np.array([look, -0.8 * look + 0.2 * rng.normal(size=(10, 3)),
                       rng.normal(size=(10, 3))])
    solver = WeightSolver(shapes, names)
    targets = eyes.EyeTargets(names, NEUTRAL, key_scale=solver.scale)
    # the points move as both keys at 0.8 would move them (the eyes read ahead)
    weights = solver.solve(0.8 * (shapes[0] + shapes[1]), *targets.rows(NEUTRAL))
    assert weights[0] < 0.1 and weights[1] < 0.1, weights
    # the eyes read looking in by 15 degrees: the right eye's In at 0.5, its Out at 0
    looking = eyes.EyeReading(NEUTRAL.upper, NEUTRAL.lower, np.zeros((2, 2)))
    looking.iris[:, 0] = eyes.EYE_RADIUS_WIDTHS * np.sin(np.radians(15))
    weights = solver.solve(0.8 * (shapes[0] + shapes[1]), *eyes.EyeTargets(
        names, NEUTRAL, key_scale=solver.scale).rows(looking))
    assert weights[0] == pytest.approx(0.5, abs=0.1) and weights[1] < 0.1, weights
