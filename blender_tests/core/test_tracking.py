"""core.tracking: shape-model fit with head pose, neutral calibration, filters (docs/method.md §11).

Known answers come from a synthetic take: the bundled ICT head, posed with known expression
weights and a known head rotation, sampled where the canonical face's 468 points lie on it,
projected through a known camera with pixel noise. test_retarget.py reuses the same take.
"""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from exclone_addon.core.errors import ExCloneError
from exclone_addon.core.retarget import locate_canonical_face
from blender_tests.helpers.takes import (CALIBRATION_FRAMES, FPS, IMAGE_SIZE, ict_rig,
                                         rotation_errors_deg, synthetic_take, tracked_take)
from exclone_addon.core.tracking import (FRONTAL, Camera, OneEuroFilter, RotationFilter,
                                         ShapeFitter, calibrate_neutral,
                                         remove_head_motion)

def test_camera_defaults_and_projection():
    cam = Camera.from_image_size(640, 480)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (640.0, 640.0, 320.0, 240.0)
    given = Camera.from_image_size(640, 480, fx=500, fy=510, cx=300, cy=200)
    assert (given.fx, given.fy, given.cx, given.cy) == (500.0, 510.0, 300.0, 200.0)
    np.testing.assert_allclose(cam.project(np.array([[0.0, 0.0, 10.0], [1.0, -2.0, 10.0]])),
                               [[320, 240], [384, 112]])
    # the analytic Jacobian matches finite differences
    p = np.array([[1.0, -2.0, 10.0]])
    numeric = np.stack([(cam.project(p + e) - cam.project(p - e))[0] / 2e-6
                        for e in 1e-6 * np.eye(3)], axis=1)
    np.testing.assert_allclose(cam.jacobian(p)[0], numeric, rtol=1e-6)
    with pytest.raises(ExCloneError, match="image size"):
        Camera.from_image_size(0, 480)


def test_canonical_face_located_on_the_ict_face():
    rig = ict_rig()
    start, stop = rig.library.parts["face"]
    assert np.all((rig.locations.corners >= start) & (rig.locations.corners < stop))
    np.testing.assert_allclose(rig.locations.bary.sum(axis=1), 1.0)
    # the canonical face's layout survives: eye and mouth corners keep their left-right order
    # and the nose tip (landmark 1 or 4) is the most forward midline point
    x = rig.neutral[:, 0]
    assert x[33] < x[133] < x[362] < x[263]       # right outer/inner, left inner/outer eye corner
    assert x[61] < x[291]                          # mouth corners
    midline = [1, 4, 6, 10, 152, 168, 197, 13, 14]
    assert rig.neutral[midline, 2].argmax() in (0, 1)


def test_default_location_keeps_off_teeth_eyeballs_and_lashes():
    """Without a given skin, the points snap onto the avatar's main connected part. On ICT that
    part also holds the mouth and eye sockets (connected to the face): points may land there."""
    rig = ict_rig()
    locations, _ = locate_canonical_face(rig.canonical, rig.library.mesh)
    parts = rig.library.parts
    corner = locations.corners[:, 0]
    in_part = {name: int(np.count_nonzero((corner >= a) & (corner < b))) for name, (a, b) in parts.items()}
    print(f"\ndefault location on ICT, points per part: {in_part}")
    for name in ("gums_and_tongue", "teeth", "eyeballs", "eye_blend_occlusion", "eyelashes"):
        assert in_part[name] == 0
    assert in_part["face"] >= 400


def test_shape_model_modes_span_the_examples():
    from exclone_addon.core.registration import similarity_transform
    rig = ict_rig()
    model = rig.model
    k = len(model.eigenvalues)
    flat = model.modes.reshape(k, -1)
    np.testing.assert_allclose(flat @ flat.T, np.eye(k), atol=1e-9)
    assert np.all(np.diff(model.eigenvalues) <= 0)
    np.testing.assert_allclose(model.mean, rig.canonical.vertices)
    # the expressions, in the canonical face's frame, are reproduced by the kept modes
    r, s, _ = similarity_transform(rig.neutral, rig.canonical.vertices)
    examples = (s * rig.deltas @ r.T).reshape(len(rig.deltas), -1)
    kept = ((examples @ flat.T) ** 2).sum() / (examples ** 2).sum()
    # and their prior variance is that of weights uniform in 0..1 (second moment 1/3)
    np.testing.assert_allclose(model.eigenvalues.sum(), (examples ** 2).sum() / 3 * kept, rtol=1e-9)
    print(f"\nshape model: {k} modes from {len(rig.deltas)} ICT expressions, {100 * kept:.3f}% kept")
    assert kept >= 0.9999


def test_fit_recovers_a_known_pose_from_exact_points():
    rig = ict_rig()
    cam = Camera.from_image_size(*IMAGE_SIZE)
    model = rig.model
    truth_b = 0.5 * np.sqrt(model.eigenvalues)
    truth_rotation = Rotation.from_euler("yxz", [20, -10, 5], degrees=True) * FRONTAL
    truth_t = np.array([2.0, 1.0, 50.0])
    points = cam.project(truth_rotation.apply(model.shape(truth_b)) + truth_t)
    fit = ShapeFitter(model, cam, beta=1e-6).fit(points)
    assert np.degrees((fit.rotation.inv() * truth_rotation).magnitude()) < 0.05
    np.testing.assert_allclose(fit.translation, truth_t, atol=0.05)
    np.testing.assert_allclose(fit.params, truth_b, atol=0.02 * np.sqrt(model.eigenvalues[0]))
    assert fit.residuals.max() < 0.01
    # points given zero confidence are ignored, whatever they hold
    garbage = points.copy()
    garbage[::3] = [[10.0, 10.0]]
    confidence = np.ones(len(points))
    confidence[::3] = 0.0
    fit = ShapeFitter(model, cam, beta=1e-6).fit(garbage, weights=confidence)
    assert np.degrees((fit.rotation.inv() * truth_rotation).magnitude()) < 0.05


def test_fit_recovers_from_a_stale_warm_start():
    """Warm-started from a fit a second earlier (head turned far since), the fit still lands on
    the same pose as the frame-by-frame one."""
    take, tracked = synthetic_take(), tracked_take()
    k = 120
    stale = tracked.fits[k - 30]
    turned = np.degrees((tracked.fits[k].rotation * stale.rotation.inv()).magnitude())
    fit = tracked.fitter.fit(take.points[k], previous=stale)
    print(f"\nstale warm start {turned:.1f} deg away: {fit.iterations} iterations")
    assert turned > 10
    assert np.degrees((fit.rotation.inv() * tracked.fits[k].rotation).magnitude()) < 0.2


def test_closed_loop_head_rotation_within_2_degrees():
    take, tracked = synthetic_take(), tracked_take()
    errors = rotation_errors_deg(take, tracked.fits)
    # the same from Kabsch (remove_head_motion) on camera-space shapes against the first frame
    rigid = tracked.fitter.model.rigid_weights()
    first = tracked.fits[0].camera_points()
    kabsch = np.array([np.degrees((remove_head_motion(f.camera_points(), first, rigid)[1].inv()
                                   * take.rotations[k] * take.rotations[0].inv()).magnitude())
                       for k, f in enumerate(tracked.fits)])
    print(f"\nhead rotation error (deg, 1 px noise): fit max {errors.max():.2f} mean {errors.mean():.2f}; "
          f"Kabsch max {kabsch.max():.2f} mean {kabsch.mean():.2f}; true range "
          f"{np.degrees(take.rotations.magnitude()).max():.1f} deg")
    print(f"fit per frame: median {np.median(tracked.fit_ms):.2f} ms, 95th pct "
          f"{np.percentile(tracked.fit_ms, 95):.2f} ms, iterations median "
          f"{np.median([f.iterations for f in tracked.fits]):.0f}; calibration "
          f"{tracked.calibration_s:.2f} s for {CALIBRATION_FRAMES} frames")
    assert errors.max() <= 2.0
    assert kabsch.max() <= 3.0


def test_outliers_do_not_drag_the_head_pose():
    take, tracked = synthetic_take(0.2), tracked_take(0.2)
    errors = rotation_errors_deg(take, tracked.fits)
    weights = np.array([f.weights for f in tracked.fits])
    print(f"\n20% outliers: head rotation error max {errors.max():.2f} mean {errors.mean():.2f} deg; "
          f"robust weight of outliers {weights[take.outliers].mean():.3f}, inliers "
          f"{weights[~take.outliers].mean():.3f}; fit median {np.median(tracked.fit_ms):.2f} ms")
    assert errors.max() <= 3.0
    assert weights[take.outliers].mean() < 0.1
    assert weights[~take.outliers].mean() > 0.8


def test_calibration_learns_the_actor_neutral():
    """The calibrated neutral matches the true (ICT) landmarks up to a similarity; the canonical
    mean it started from does not."""
    from exclone_addon.core.registration import similarity_transform
    rig, tracked = ict_rig(), tracked_take()

    def misfit(shape):
        r, s, t = similarity_transform(shape, rig.neutral)
        return np.sqrt(((s * shape @ r.T + t - rig.neutral) ** 2).sum(axis=1).mean())

    before, after = misfit(rig.model.mean), misfit(tracked.neutral)
    print(f"\nneutral vs true landmarks (RMS cm after similarity): canonical {before:.3f}, "
          f"calibrated {after:.3f}")
    assert after < 0.1 and after < 0.35 * before


def test_remove_head_motion_known_answer():
    rng = np.random.default_rng(1)
    neutral = rng.normal(size=(50, 3))
    displacement = np.zeros_like(neutral)
    displacement[:5] = rng.normal(scale=0.05, size=(5, 3))
    turn = Rotation.from_euler("xyz", [10, -25, 5], degrees=True)
    frame = turn.apply(neutral + displacement) + [3.0, -1.0, 2.0]
    weights = np.ones(50)
    weights[:5] = 0.0                      # the moving points do not vote on the head pose
    aligned, rotation = remove_head_motion(frame, neutral, weights)
    assert np.degrees((rotation.inv() * turn).magnitude()) < 1e-6
    np.testing.assert_allclose(aligned - neutral, displacement, atol=1e-9)
    # a mirrored frame cannot be matched by a reflection: the result stays a proper rotation
    _, rotation = remove_head_motion(frame * [-1, 1, 1], neutral)
    assert np.linalg.det(rotation.as_matrix()) > 0
    with pytest.raises(ExCloneError):
        remove_head_motion(frame[:10], neutral)


def test_one_euro_filter_removes_jitter_and_keeps_fast_motion():
    rng = np.random.default_rng(2)
    t = np.arange(300) / FPS
    steady = 5.0 + rng.normal(0.0, 1.0, len(t))
    flt = OneEuroFilter(min_cutoff=1.0, beta=0.05)
    out = np.array([flt(x, s) for x, s in zip(steady, t)])
    assert out[30:].std() < 0.4 * steady[30:].std()
    # without speed adaptation it is exactly the exponential smoother of cut-off min_cutoff
    from scipy.signal import lfilter
    alpha = 1.0 / (1.0 + FPS / (2 * np.pi * 1.0))
    fixed = OneEuroFilter(min_cutoff=1.0, beta=0.0)
    expected, _ = lfilter([alpha], [1.0, alpha - 1.0], steady[1:], zi=[(1 - alpha) * steady[0]])
    np.testing.assert_allclose([fixed(x, s) for x, s in zip(steady, t)][1:], expected, rtol=1e-12)
    # a fast ramp (300 units/s): the adaptive cut-off follows it with far less lag than the
    # same filter without speed adaptation
    ramp = 300.0 * t
    lag_adaptive = ramp[-1] - [OneEuroFilter(1.0, 0.05)(x, s) for x, s in zip(ramp, t)][-1]
    fixed = OneEuroFilter(1.0, 0.0)
    lag_fixed = ramp[-1] - [fixed(x, s) for x, s in zip(ramp, t)][-1]
    assert lag_adaptive < 0.1 * lag_fixed
    # rotations: jitter of 1 degree about a fixed pose is reduced
    base = Rotation.from_euler("y", 20, degrees=True)
    noisy = [Rotation.from_rotvec(np.radians(rng.normal(0, 1.0, 3))) * base for _ in t]
    rf = RotationFilter(min_cutoff=1.0, beta=0.5)
    smoothed = [rf(r, s) for r, s in zip(noisy, t)]
    err_in = np.mean([np.degrees((r * base.inv()).magnitude()) for r in noisy[30:]])
    err_out = np.mean([np.degrees((r * base.inv()).magnitude()) for r in smoothed[30:]])
    assert err_out < 0.5 * err_in


def test_fit_rejects_bad_input():
    rig = ict_rig()
    fitter = ShapeFitter(rig.model, Camera.from_image_size(*IMAGE_SIZE))
    with pytest.raises(ExCloneError, match="468"):
        fitter.fit(np.zeros((68, 2)))
    with pytest.raises(ExCloneError, match="fewer than 6"):
        fitter.fit(np.full((468, 2), np.nan))
    with pytest.raises(ExCloneError, match="at least one frame"):
        calibrate_neutral(fitter, np.zeros((0, 468, 2)))
