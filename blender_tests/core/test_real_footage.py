"""What real footage brings, on a real photograph (skimage's astronaut, public domain) pasted into
1080p frames: a small face (80 pixels wide) in a large frame, two faces of which the take
follows one, a face that leaves the frame and comes back. Tracked by FaceTrackingSession.step,
as a camera's frames are."""
import cv2
import numpy as np
import pytest

from exclone_addon.core import face_models
from exclone_addon.core.session import FaceTrackingSession
from blender_tests.core.test_face_models import HAND_IOD, HAND_POINTS
from blender_tests.helpers.takes import astronaut

FRAME = (1920, 1080)
FPS = 30.0
NOSE = np.array(HAND_POINTS[30])          # the nose tip in the photograph
NOSE_ID = face_models.IBUG68_FROM_MEDIAPIPE[30]
# the face's width in the photograph: about 1.45 eye distances (cheek to cheek)
FACE_WIDTH = 1.45 * HAND_IOD


def pasted(faces, size=FRAME):
    """A grey frame (with a little noise) holding the photograph once per (nose x, nose y, face
    width in pixels); returns the frame and each face's nose position."""
    rng = np.random.default_rng(0)
    frame = rng.integers(95, 105, (size[1], size[0], 3)).astype(np.uint8)
    noses = []
    for x, y, width in faces:
        scale = width / FACE_WIDTH
        matrix = np.array([[scale, 0.0, x - scale * NOSE[0]], [0.0, scale, y - scale * NOSE[1]]])
        photo = cv2.warpAffine(astronaut(), matrix, size, flags=cv2.INTER_AREA)
        mask = cv2.warpAffine(np.full(astronaut().shape[:2], 255, np.uint8), matrix, size)
        frame[mask > 127] = photo[mask > 127]
        noses.append(np.array([x, y], float))
    return frame, noses


def track(frames):
    """Each frame through one session: (found per frame, nose tip per frame or None)."""
    session = FaceTrackingSession(calibration_frames=3)
    found, noses = [], []
    for k, frame in enumerate(frames):
        result = session.step(frame, k / FPS)
        found.append(result.found)
        noses.append(result.landmarks[NOSE_ID, :2] if result.found else None)
    return found, noses


def test_a_small_face_in_a_1080p_frame_is_found_and_followed():
    # the whole frame letterboxed into BlazeFace's 128 pixels leaves this face 5 pixels wide
    first, _ = pasted([(1400, 620, 80)])
    assert face_models.FaceDetector().detect(first) == []
    path = [(1400 - 15 * k, 620 + 4 * k, 80) for k in range(12)]
    frames, truths = zip(*(pasted([face]) for face in path))
    found, noses = track(frames)
    assert all(found)
    errors = [np.linalg.norm(nose - truth[0]) for nose, truth in zip(noses, truths)]
    assert max(errors) < 0.08 * 80, errors


@pytest.mark.parametrize("large_first", [True, False])
def test_of_two_faces_the_take_follows_the_larger_and_never_jumps(large_first):
    """Two copies, 150 and 100 pixels wide, moving towards and past each other's height."""
    frames, larges = [], []
    for k in range(12):
        large, small = (500 + 20 * k, 400 + 10 * k, 150), (1300 - 20 * k, 700 - 15 * k, 100)
        faces = [large, small] if large_first else [small, large]
        frame, noses = pasted(faces)
        frames.append(frame)
        larges.append(noses[0 if large_first else 1])
    found, noses = track(frames)
    assert all(found)
    errors = [np.linalg.norm(nose - large) for nose, large in zip(noses, larges)]
    assert max(errors) < 0.08 * 150, errors


def test_a_face_that_leaves_and_comes_back_is_found_again_and_a_bystander_is_not_taken():
    """The followed face (120 px) is out of the frame on the right for 8 frames while a
    smaller one (80 px) stays in view, then comes back at another place."""
    frames, truths = [], []
    for k in range(22):
        if k < 6:
            followed = (1500 + 15 * k, 500, 120)
        elif k < 14:
            followed = (2400, 500, 120)                    # outside the frame
        else:
            followed = (900 + 10 * k, 300, 120)
        frame, noses = pasted([followed, (400, 800, 80)])
        frames.append(frame)
        truths.append(noses[0] if followed[0] < FRAME[0] else None)
    found, noses = track(frames)
    for k, (nose, truth) in enumerate(zip(noses, truths)):
        if truth is None:
            assert not found[k], f"frame {k}: the bystander was taken up"
        else:
            assert found[k], f"frame {k}: the face was not found"
            assert np.linalg.norm(nose - truth) < 0.08 * 120, (k, nose, truth)
