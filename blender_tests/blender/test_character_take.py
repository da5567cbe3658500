"""Tracking through the image models onto a character no build step learns from: a MakeHuman
body (../shared/data/characters) given the ARKit keys by Clone, rendered wearing them with known
weights of the 17 driven shapes and a known head turn (blender_tests/helpers/character_takes.py),
tracked frame by frame by FaceTrackingSession.step onto the same character as a user's avatar (the
tracker's points located on its body as Drive from Webcam locates them), so the ideal answer is
the truth. The tracker model, the eyes' slide and the appearance map were learnt from ICT heads:
this face differs in topology, look and proportions. Figures as test_rendered_takes' (measured,
checked with a margin; the targets as strict expected failures)."""
import numpy as np
import pytest

from blender_tests.helpers.character_takes import (CHARACTER, cloned_character,
                                                   rendered_character_take, tracked_take_fixtures)
from blender_tests.helpers.takes import (assert_pose_as_measured, assert_pose_reaches_target,
                                         largest_false_weight, unit_scores)

moving, still, turning = tracked_take_fixtures(rendered_character_take)


@pytest.mark.parametrize("file_name, shapes", [(CHARACTER, None),
                                               ("mh_female_old_body.fbx", "jawOpen,eyeBlink_L")])
def test_the_avatars_face_is_found_on_the_body(file_name, shapes, shared_data):
    """The tracker's points are located on the body's face as Clone finds it (the face found by
    rendering, the head region cut from the body): a face's size, the eye corners about the
    eyeballs. Before, the canonical face was registered onto the whole body: here no face was
    found on either (1 and 3 landmarks); through the add-on's avatar_rig the old woman's FBX
    (Y-up centimetres, its rotation and scale left on the objects) got one spread over the upper
    body (62 x 54 cm, the eye corners 16.6 cm below the eyes) without an error."""
    character = cloned_character(file_name, shapes)
    eyeballs = np.vstack([vertices for name, vertices, _, _ in character.meshes
                          if name.lower().startswith("eye") and "brow" not in name.lower()
                          and "lash" not in name.lower()])
    points = character.located
    eye_distance = np.linalg.norm(points[33] - points[263])
    assert np.all(np.ptp(points, axis=0)[:2] < 3.0 * eye_distance), np.ptp(points, axis=0)
    corners = points[[33, 133, 362, 263]].mean(axis=0)
    assert np.all(np.abs(corners - eyeballs.mean(axis=0))[:2] < 0.1 * eye_distance), (
        corners, eyeballs.mean(axis=0))


def _figures(take, tracked):
    scores = unit_scores(take, tracked)
    correlations = np.array([c for c, _ in scores.values()])
    text = ", ".join(f"{unit} {c:.2f}" for unit, (c, _) in scores.items())
    return correlations, np.mean([e for _, e in scores.values()]), text


# Measured (mean correlation over the 17 driven shapes, MAE): the head moving 0.754, 0.044 (the
# lowest browDown_L -0.09, mouthFrown_R 0.42, browDown_R 0.52); still 0.936, 0.022 (the lowest
# browDown_L 0.61, browDown_R 0.85). Before the actor's neutral reading followed the head's turn
# (core.appearance.NeutralReading): 0.713, 0.046. Before the appearance's grid read a smoothed
# image and its weights were filtered over time (stop 39): 0.704, 0.047 (read at a median 0.33 of
# their size); 0.930, 0.021. Without the face's appearance, moving: 0.436, 0.092. After a wide
# calibration (helpers.takes, "wide"), moving: 0.728, 0.042. On the ICT heads the moving takes read
# 0.93-0.95: here the head's motion costs the most (the rotation below).
MEASURED_WEIGHTS = {"moving": (0.73, 0.047), "still": (0.90, 0.025)}


@pytest.mark.parametrize("take_name", sorted(MEASURED_WEIGHTS))
def test_weights_follow_the_characters_face_as_measured(take_name, request):
    correlations, mae, text = _figures(*request.getfixturevalue(take_name))
    least_mean, most_mae = MEASURED_WEIGHTS[take_name]
    assert correlations.mean() >= least_mean and mae <= most_mae, f"MAE {mae:.3f}; {text}"


@pytest.mark.xfail(strict=True, reason="measured: 0.754 with the head moving (browDown_L -0.09, "
                                       "mouthFrown_R 0.42, browDown_R 0.52), MAE 0.044; 0.936 "
                                       "with it still but browDown_L 0.61")
@pytest.mark.parametrize("take_name", ["moving", "still"])
def test_weights_reach_the_target(take_name, request):
    correlations, mae, text = _figures(*request.getfixturevalue(take_name))
    assert correlations.mean() >= 0.85 and correlations.min() >= 0.7 and mae <= 0.08, text


# Measured (median, max rotation error in degrees; per-axis slopes pitch, yaw, roll): moving
# 3.04, 6.15 (1.11, 1.12, 0.98); the neutral face turning 2.86, 6.81 (1.08, 1.10, 1.02); before
# stop 39 2.99, 5.95 and 2.84, 6.73. After a
# wide calibration, moving: 2.13, 4.25 (1.08, 1.05, 0.98). The turn reads about a tenth too large
# about both axes: the calibrated neutral is flatter than this face (its depth against the
# true points' 1 : 1.077; the tracker model's mean 1 : 1.048; ICT heads 1 : 1.04), which a
# one-second calibration turning 10 deg cannot see (the wide one: 1 : 1.011).
MEASURED_POSE = {"moving": (3.2, 6.3), "turning": (3.0, 7.1)}
SLOPE_RANGE = (0.95, 1.15)


@pytest.mark.parametrize("take_name", sorted(MEASURED_POSE))
def test_head_rotation_as_measured(take_name, request):
    assert_pose_as_measured(*request.getfixturevalue(take_name), *MEASURED_POSE[take_name],
                            SLOPE_RANGE)


@pytest.mark.xfail(strict=True, reason="measured: median 3.04 deg, max 6.15 deg, pitch and yaw "
                                       "at 1.11 and 1.12 of their size (see MEASURED_POSE)")
def test_head_rotation_reaches_the_target(moving):
    assert_pose_reaches_target(*moving)


# Measured on the neutral face turning up to 30 deg: the largest weight 0.50 (eyeLookIn_L, the
# gaze; 0.50 too onto the ICT head as the avatar: the iris model's reading of these eyes slides
# more with the turn than an ICT head's, 0.30), the keys the eyes do not read 0.24 (browOuterUp_L;
# 0.31 before stop 39). Before the RBF's smoothing was in the actor's units (core.retarget
# map_blendshapes: this avatar is in metres) 0.72 (eyeWide_R); before each eyeLook pair's sum was
# held to the gaze's size (core.eyes) 1.00, eyeLookOut_R and eyeLookIn_R together. Checked with a
# margin.
MEASURED_FALSE_WEIGHT = {"": 0.54, "eye": 0.54, "others": 0.28}


@pytest.mark.parametrize("keys", sorted(MEASURED_FALSE_WEIGHT))
def test_a_turning_neutral_face_as_measured(turning, keys):
    value, name = (largest_false_weight(*turning, but="eye") if keys == "others"
                   else largest_false_weight(*turning, only=keys))
    assert value <= MEASURED_FALSE_WEIGHT[keys], f"{name} reached {value:.2f}"


@pytest.mark.xfail(strict=True, reason="measured: 0.50 (eyeLookIn_L, the gaze), the keys the "
                                       "eyes do not read 0.24 (browOuterUp_L)")
def test_a_turning_neutral_face_makes_no_expression(turning):
    value, name = largest_false_weight(*turning)
    assert value <= 0.15, f"{name} reached {value:.2f}"
