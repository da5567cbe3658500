"""Tracking through the image models on rendered takes (blender_tests/helpers/takes.py): an
ICT-topology head posed with known weights of 17 driven shapes and a known head turn, rendered
in background Blender at 640x480, tracked frame by frame by FaceTrackingSession.step (what a
camera feeds) onto the same head, so the ideal answer is the truth.

Two kinds of test: the figures measured today, asserted with a small margin (a change that makes
tracking worse fails them), and the figures tracking should reach, as strict expected failures
(a change that reaches them makes them pass, which fails the run until the mark is removed and
the measured bounds raised). The renders are cached in the temp directory: only the first run
renders (about 0.35 CPU s a frame, 220 frames a take).
"""
import numpy as np
import pytest

from blender_tests.helpers.takes import (largest_false_weight, pose_errors, rendered_take,
                                         track_rendered, unit_scores)

# An ICT identity (the identity model's weights for this seed), not the bundled face.
OTHER_IDENTITY = 7

# Measured (mean correlation over the 17 driven shapes, their mean absolute error):
# bundled head 0.320, 0.070; identity 7: 0.350, 0.067.
MEASURED_WEIGHTS = {"moving": (0.28, 0.076), "other_identity": (0.31, 0.073)}
# Measured (median, max rotation error in degrees; per-axis slopes pitch, yaw, roll):
# moving 2.20, 6.4, (0.87, 1.00, 0.99); turning 2.45, 7.0, (0.85, 0.99, 1.02);
# identity 7: 2.26, 6.9, (0.86, 1.01, 0.98). (2D points alone, every point counted alike:
# moving 2.93, 6.1, pitch 0.78; turning 3.45, 7.0, pitch 0.77.)
MEASURED_POSE = {"moving": (2.7, 7.6), "turning": (2.9, 8.3), "other_identity": (2.8, 8.2)}
SLOPE_RANGE = (0.8, 1.12)


@pytest.fixture(scope="module")
def moving():
    take = rendered_take("moving")
    return take, track_rendered(take)


@pytest.fixture(scope="module")
def turning():
    take = rendered_take("turning")
    return take, track_rendered(take)


@pytest.fixture(scope="module")
def other_identity(shared_data):
    take = rendered_take("moving", identity=OTHER_IDENTITY)
    return take, track_rendered(take)


def _weight_figures(take, tracked):
    scores = unit_scores(take, tracked)
    correlations = np.array([c for c, _ in scores.values()])
    errors = np.array([e for _, e in scores.values()])
    text = ", ".join(f"{unit} {c:.2f}" for unit, (c, _) in scores.items())
    return correlations, errors.mean(), text


@pytest.mark.parametrize("take_name", sorted(MEASURED_WEIGHTS))
def test_weights_follow_the_rendered_face_as_measured(take_name, request):
    correlations, mae, text = _weight_figures(*request.getfixturevalue(take_name))
    least_mean, most_mae = MEASURED_WEIGHTS[take_name]
    assert correlations.mean() >= least_mean and mae <= most_mae, f"MAE {mae:.3f}; {text}"


@pytest.mark.parametrize("take_name", sorted(MEASURED_POSE))
def test_head_rotation_as_measured(take_name, request):
    errors, slopes = pose_errors(*request.getfixturevalue(take_name))
    most_median, most_max = MEASURED_POSE[take_name]
    assert np.median(errors) <= most_median and errors.max() <= most_max, (np.median(errors), errors.max())
    low, high = SLOPE_RANGE
    assert np.all((slopes >= low) & (slopes <= high)), slopes


@pytest.mark.xfail(strict=True, reason="measured: mean correlation 0.32, most shapes below 0.7, "
                                       "MAE 0.070 (bundled head, head moving up to 25 deg)")
def test_weights_reach_the_target(moving):
    correlations, mae, text = _weight_figures(*moving)
    assert correlations.mean() >= 0.85 and correlations.min() >= 0.7 and mae <= 0.08, text


@pytest.mark.xfail(strict=True, reason="measured: a neutral face turning up to 30 deg reaches "
                                       "weight 0.91 (browDown_L); with the true points' "
                                       "projections 0.04: FaceMesh's points slide as the head turns")
def test_a_turning_neutral_face_makes_no_expression(turning):
    value, name = largest_false_weight(*turning)
    assert value <= 0.15, f"{name} reached {value:.2f}"


@pytest.mark.xfail(strict=True, reason="measured: median 2.2 deg, max 6.4 deg, pitch read at 0.87 "
                                       "(the true points' projections instead of FaceMesh's "
                                       "on the turning take: 0.8, 1.9, every axis 1.00)")
def test_head_rotation_reaches_the_target(moving):
    errors, slopes = pose_errors(*moving)
    assert np.median(errors) <= 1.5 and errors.max() <= 3.0
    assert np.all(np.abs(slopes - 1) <= 0.05), slopes
