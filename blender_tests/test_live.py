"""core.live: the per-frame tracking session (issue 5), on known answers.

- the synthetic ICT take of test_tracking (known weights and head rotation) fed past the image
  models into the session: weights and head rotation as in the closed-loop tests;
- head rotation in Blender's axes on exact, known poses;
- a real photograph (skimage's astronaut) moved by known translations, rotations and scales:
  the tracked points follow the motion; frames without a face: the pose is held, then tracking
  resumes;
- chessboard camera calibration on synthetic views with known intrinsics;
- the shipped tracker model is current.
"""
import functools

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from skimage import data

from exclone_addon.core import live
from exclone_addon.core.errors import ExCloneError
from exclone_addon.core.face_models import IBUG68_FROM_MEDIAPIPE
from exclone_addon.core.live import (MODEL_TO_BLENDER, AvatarRig, FaceTrackingSession,
                                     TrackerModel, calibrate_camera, load_tracker_model)
from exclone_addon.core.tracking import FRONTAL, Camera
from test_tracking import CALIBRATION_FRAMES, FPS, ict_rig, synthetic_take


@functools.lru_cache(maxsize=1)
def ict_avatar():
    """The ICT library as the avatar, located with test_tracking's (cached) registration."""
    rig = ict_rig()
    return AvatarRig.from_locations(rig.library.mesh.vertices, rig.library.deltas,
                                    rig.library.names, rig.locations)


@functools.lru_cache(maxsize=1)
def session_on_synthetic_take():
    """The closed loop's tracker model comes from the same registration as the take (as in
    test_tracking), not from the shipped file, so that it checks the session, not staleness."""
    take = synthetic_take()
    session = FaceTrackingSession(avatar=ict_avatar(), camera=take.camera,
                                  calibration_frames=CALIBRATION_FRAMES,
                                  tracker_model=TrackerModel.from_locations(ict_rig().locations))
    results = [session.step_landmarks(points, k / FPS) for k, points in enumerate(take.points)]
    return take, session, results


def test_shipped_tracker_model_is_current():
    # derived data: stale after a change of the library, the canonical face or the engine. The
    # located points are compared (not triangle ids: a point on an edge may change triangle)
    rig = ict_rig()
    fresh = rig.locations.sample(rig.library.mesh.vertices)
    shipped = live.read_tracker_locations().sample(rig.library.mesh.vertices)
    moved = np.linalg.norm(fresh - shipped, axis=1)       # cm on ICT's 15 cm wide face
    assert moved.max() < 0.02, f"points moved up to {moved.max():.3f} cm: run scripts/make_tracker_model.py"


def test_session_closed_loop_weights_and_head_rotation():
    """The synthetic take through the session (filters included): weights track the truth as
    in test_retarget's closed loop, head rotation relative to the calibrated neutral within 2
    degrees.

    Judged on the frames after calibration only. test_retarget's closed loop (no filters) also
    counts the 30 calibration frames, whose weights are all zero; on the later frames alone it
    measures mouthPucker's correlation 0.84 (0.925 with them), the others >= 0.95, MAE 0.059.
    """
    take, session, results = session_on_synthetic_take()
    assert all(r.found for r in results)
    assert [r.status.startswith("calibrating") for r in results[:CALIBRATION_FRAMES - 1]] == \
        [True] * (CALIBRATION_FRAMES - 1)
    assert all(r.weights is None for r in results[:CALIBRATION_FRAMES - 1])
    tracked = results[CALIBRATION_FRAMES - 1:]     # the calibration ends on frame 29
    names = session.solver.names
    weights = np.array([[r.weights[n] for n in names] for r in tracked])
    truth = take.weights[CALIBRATION_FRAMES - 1:]
    active = take.active
    corr = np.array([np.corrcoef(weights[:, j], truth[:, j])[0, 1] for j in active])
    mae = np.abs(weights[:, active] - truth[:, active]).mean()
    # head rotation: the truth relative to the mean pose of the calibration frames, in Blender axes
    true_model = take.rotations * FRONTAL
    neutral = true_model[:CALIBRATION_FRAMES].mean()
    # the take's head jumps 27 degrees from its calibration motion at frame 30: the filter
    # smooths a jump over a few frames by design, so those frames are left out
    errors = np.degrees([((MODEL_TO_BLENDER * neutral.inv() * true_model[k] * MODEL_TO_BLENDER.inv()).inv()
                          * r.head_rotation).magnitude()
                         for k, r in enumerate(results) if k >= CALIBRATION_FRAMES + 6])
    print(f"\nsession closed loop: 10 active corr mean {corr.mean():.3f} min {corr.min():.3f}, "
          f"MAE {mae:.3f}; head rotation error max {errors.max():.2f} mean {errors.mean():.2f} deg")
    assert corr.min() >= 0.8 and np.median(corr) >= 0.95
    assert mae <= 0.07
    assert errors.max() <= 2.5
    assert len(session.take.timestamps) == len(tracked)


def test_head_rotation_in_blender_axes():
    """A head turned to the subject's own left turns about Blender's +Z; looking up turns the
    forward axis (-Y) up towards +Z."""
    model = load_tracker_model().shape_model
    camera = Camera.from_image_size(640, 480)
    session = FaceTrackingSession(camera=camera, calibration_frames=3)

    def frame(camera_rotation):
        pose = camera_rotation * FRONTAL
        return camera.project(pose.apply(model.mean) + [0.0, 0.0, 50.0])

    for k in range(3):
        session.step_landmarks(frame(Rotation.identity()), k / FPS)
    assert session.calibrated
    # subject's left = camera +x: the face's direction (camera -z) turns towards +x
    left = Rotation.from_euler("y", -20, degrees=True)
    up = Rotation.from_euler("x", -15, degrees=True)            # image up is camera -y
    for k, (turn, forward) in enumerate([(left, [np.sin(np.radians(20)), -np.cos(np.radians(20)), 0]),
                                         (up, [0, -np.cos(np.radians(15)), np.sin(np.radians(15))])]):
        # 2 s of the pose so the filters settle
        for j in range(60):
            result = session.step_landmarks(frame(turn), (3 + 100 * k + j) / FPS)
        np.testing.assert_allclose(result.head_rotation.apply([0.0, -1.0, 0.0]), forward, atol=0.01)


def test_refine_take_from_the_session():
    _, session, results = session_on_synthetic_take()
    timestamps, weights, names = session.refine_take(closeness=1.0, iterations=3)
    assert names == session.solver.names
    assert weights.shape == (len(results) - CALIBRATION_FRAMES + 1, len(names))
    assert weights.min() >= -1e-12 and weights.max() <= 1.0 + 1e-12
    np.testing.assert_allclose(timestamps, np.arange(CALIBRATION_FRAMES - 1, len(results)) / FPS)
    with pytest.raises(ExCloneError, match="no calibrated avatar"):
        FaceTrackingSession().refine_take()


def test_avatar_without_shape_keys_or_motion_is_a_clear_error():
    rig = ict_rig()
    vertices = rig.library.mesh.vertices
    with pytest.raises(ExCloneError, match="no shape keys"):
        AvatarRig.from_arrays(vertices, rig.library.mesh.triangles(), np.zeros((0, len(vertices), 3)), [])
    with pytest.raises(ExCloneError, match="moves its face"):
        AvatarRig.from_locations(vertices, np.zeros((2, len(vertices), 3)), ["a", "b"], rig.locations)
