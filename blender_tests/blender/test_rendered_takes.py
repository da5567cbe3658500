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

from dataclasses import replace

from exclone_addon.core.tracker_model import load_tracker_model

from blender_tests.helpers.takes import (OTHER_IDENTITY, SIDE_LIGHT_TURN,
                                         assert_pose_as_measured, assert_pose_reaches_target,
                                         largest_false_weight, rendered_take, through_a_webcam,
                                         track_rendered, track_true_points, unit_scores)

# Measured with the face's appearance read beside the points (core.appearance, the map learnt from
# 96 takes of other ICT identities, scripts/make_appearance_model.py, reading the face's shading
# and edges and the points' weights, un-mixed by its learnt response with a penalty that grows with
# the head's turn from its calibrated pose; the keys it reads by name take its weight at its share
# 1.0; mean correlation over the 17 driven shapes, their mean absolute error): bundled head 0.952,
# 0.025; identity 7: 0.928, 0.028; the head still: 0.975, 0.014 (the lowest shapes: mouthFrown_R
# 0.81, mouthFrown_R 0.73 (identity 7), mouthFrown_L 0.88 (still)). With one penalty (0.1) at every
# turn: 0.963, 0.021; 0.937, 0.026; 0.967, 0.017 (mouthFrown_R 0.86, mouthStretch_R 0.71,
# mouthFrown_L 0.85). With the map's 1,500 components (2,500 now): 0.948, 0.024; 0.928, 0.027;
# 0.959, 0.019 (mouthFrown_R 0.81, mouthStretch_R 0.697, mouthFrown_L 0.85). Before the map read
# the face's edges (its shading alone, share 0.875): 0.902, 0.031; 0.916, 0.032; 0.928, 0.026 (the
# frowns the lowest: 0.70 / 0.39, 0.66 / 0.73, 0.63 / 0.52; every other shape at least 0.77).
# Before the un-mixing: 0.898, 0.038; 0.900, 0.038; 0.930, 0.032 (the frowns 0.69 / 0.51, 0.65 /
# 0.73, 0.62 / 0.62). With the un-mixing's penalty at 0.03 (chosen by the training takes' held-out
# correlation, not their squared error): 0.933, 0.025; 0.933, 0.026; 0.954, 0.019, every shape of
# identity 7 at least 0.75, but the turning face's keys the eyes do not read 0.35 and a blink's
# 0.38. With every key following the map's weights as their motion at the tracker's points: 0.859,
# 0.031; 0.866, 0.032; 0.883, 0.028 (before the un-mixing 0.853, 0.033; 0.867, 0.034; 0.899,
# 0.030). Before the map read the points' weights (share 0.75): 0.886, 0.040; 0.893, 0.042; 0.913,
# 0.034 (the frowns 0.54 / 0.63, 0.56 / 0.77, 0.55 / 0.49); every key following the motion 0.845,
# 0.035; 0.863, 0.035; 0.879, 0.032 (the frowns -0.06 / 0.51, 0.00 / 0.69, 0.33 / 0.21). Without
# the appearance, with the tracker model learnt from FaceMesh's points on other ICT identities
# (scripts/make_tracker_model.py) and the material points beside them (core.material_points):
# bundled head 0.654, 0.051; identity 7: 0.721, 0.049; the head still: 0.768, 0.044 (with only the
# material points' pull across the head's motion smaller than along it: 0.592, 0.053; 0.674, 0.049;
# 0.743, 0.043; with only the keys the eyes do not read solved from the landmarks alone: 0.592,
# 0.052; 0.675, 0.051; 0.756, 0.045; before both: 0.548, 0.055; 0.633, 0.050; 0.731, 0.043; before
# the flow followed the frames less their blur, the pull 0.3 per pixel: 0.521, 0.057; 0.600, 0.052;
# 0.691, 0.044; before the material points' pull to FaceMesh's fit grew with the head's motion, a
# fixed 0.2 a frame: 0.503, 0.056; 0.570, 0.053; 0.639, 0.046; before the material points' refit
# carried a turn of their own and refined their depths: 0.468, 0.060; 0.550, 0.058; 0.630, 0.047;
# before the eyes' learnt slide and the turned eyes' lid rows weighed down: 0.476, 0.060; 0.526,
# 0.061; 0.634, 0.046; the eyes' rows join the solve). (FaceMesh's points alone: 0.325, 0.056;
# 0.365, 0.059; 0.517, 0.046. With the model of the located points the learnt one replaced: 0.320,
# 0.067; 0.343, 0.067.) Through a webcam (takes.through_a_webcam: sensor noise of 10 of 255, JPEG
# at 80) the moving take reads 0.929, 0.029 (mouthFrown_R 0.69; identity 7 0.922, the head still
# 0.968); 0.928, 0.030 (0.65; 0.916, 0.968) before the actor's neutral reading followed the head's
# turn (core.appearance.NeutralReading), 0.910, 0.030 (0.61; 0.895, 0.960) before the appearance's
# weights were filtered over time (core.session), 0.866, 0.033 (0.46; 0.845, 0.937) before the
# image was also smoothed for the appearance's grid (core.appearance.GRID_ANTIALIAS). The clean
# takes now 0.952, 0.025; 0.929, 0.029; 0.973, 0.015. Lit from one side (takes.SIDE_LIGHT_TURN; the
# appearance map's training takes and every other take here are lit from the camera's side): 0.841,
# 0.040 (mouthStretch_L 0.44, mouthFrown_R 0.50); 0.812 (browDown_L 0.11) before the actor's
# neutral reading followed the turn; without the appearance 0.485, 0.079 (0.654 lit from the
# camera's side: FaceMesh's points lose some too). The light turned 0.6 rad instead (from above and
# aside, half the face in shadow; scratch): 0.591, without the appearance 0.424.
MEASURED_WEIGHTS = {"moving": (0.93, 0.028), "other_identity": (0.91, 0.031),
                    "still": (0.96, 0.017), "moving_webcam": (0.915, 0.032),
                    "moving_side_light": (0.82, 0.043)}
# The moving take with the appearance not read (the points and the eyes alone), as above: 0.654.
MEASURED_WITHOUT_APPEARANCE = 0.63
# Measured (median, max rotation error in degrees; per-axis slopes pitch, yaw, roll), the fit's
# learnt rotation bias taken out (core.tracker_model.learn_pose_bias) and then the appearance
# map's (the turn's error its un-mixed weights make: AppearanceMap.unbiased_turn): moving 1.23,
# 2.61, (0.99, 1.00, 1.00); turning 1.16, 2.84, (1.00, 1.00, 1.02); identity 7: 1.45, 3.30, (1.04,
# 1.02, 1.02); the head still 0.56, 1.85 (with one un-mixing penalty at every turn: 1.26, 2.63;
# 1.18, 2.83; 1.45, 3.28; 0.57, 1.91; with the map's 1,500 components: 1.26, 2.59; 1.17, 2.86;
# 1.44, 3.28; 0.59, 2.05; with the map reading the shading alone: 1.22, 2.61; 1.14,
# 2.91; 1.48, 3.34, pitch 1.05; 0.57, 2.04; before the un-mixing: 1.28, 2.77; 1.16, 2.84; 1.54,
# 3.55; 0.57, 1.78). (Without the map's: 1.32, 2.86; 1.16, 2.80; 1.60, 3.64, pitch 1.06; 0.61, 1.92.
# Without either: 1.45, 2.56; 1.42, 2.97; 1.55, 3.58; 0.69,
# 1.92. Turns not checked here, the biases learnt without them: ICT identities 11, 23, 31 and 42
# 1.79 / 3.28, 1.23 / 3.04, 1.49 / 3.20, 1.60 / 3.37 (identity 11's pitch at 0.90 of its size;
# with one un-mixing penalty 1.84 / 3.34, 1.24 / 3.11, 1.55 / 3.24, 1.59 / 3.42; with 1,500
# components 1.83 / 3.32, 1.24 / 3.03, 1.52 / 3.22, 1.57 / 3.41); with
# the map reading the shading alone 1.79 / 3.29, 1.18 / 2.82, 1.41 / 3.10, 1.54 / 3.16 (identity
# 11's pitch at 0.91; before the un-mixing 1.75 / 3.26, 1.25 / 3.02, 1.33 / 3.19, 1.58 / 3.41);
# without the map's bias 1.75 / 3.23, 1.35 / 3.07, 1.34 / 3.19, 1.60 / 3.47; without either 1.95 /
# 3.98, 1.57 / 3.15, 1.51 / 3.16, 1.76 / 3.59. Before the fit saw the modes as FaceMesh does and
# with the rotation's filter at 1 Hz: 1.57, 3.23; 1.48, 2.95; 1.52, 4.32. The located points' model
# with FaceMesh's
# depth, on the same frames: moving 2.23, 6.43, pitch 0.85; turning 2.47, 6.63, pitch 0.85;
# identity 7: 2.38, 6.62, pitch 0.86.)
# Lit from one side: 1.93, 3.92 (1.03, 0.94, 1.04; 1.82, 3.82 before the actor's neutral reading
# followed the turn); without the appearance 1.99, 3.77.
MEASURED_POSE = {"moving": (1.6, 3.2), "turning": (1.5, 3.3), "other_identity": (1.85, 4.3),
                 "moving_side_light": (2.0, 4.1)}
SLOPE_RANGE = (0.93, 1.09)


@pytest.fixture(scope="module")
def moving():
    take = rendered_take("moving")
    return take, track_rendered(take)


@pytest.fixture(scope="module")
def still():
    take = rendered_take("still")
    return take, track_rendered(take)


@pytest.fixture(scope="module")
def turning():
    take = rendered_take("turning")
    return take, track_rendered(take)


@pytest.fixture(scope="module")
def turning_wide():
    """The turning take after a wide calibration (the head turning yaw +-30, pitch +-20 deg)."""
    take = rendered_take("turning", calibration="wide")
    return take, track_rendered(take)


@pytest.fixture(scope="module")
def moving_webcam():
    """The moving take's frames as a webcam would deliver them (takes.through_a_webcam)."""
    take = through_a_webcam(rendered_take("moving"))
    return take, track_rendered(take)


@pytest.fixture(scope="module")
def moving_side_light():
    """The moving take lit from one side (takes.SIDE_LIGHT_TURN), a light no build step saw."""
    take = rendered_take("moving", light_turn=SIDE_LIGHT_TURN)
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


# The same moving take on ICT identities no build step learns from (seeds of the identity model):
# measured (mean correlation, MAE) 11: 0.905, 0.027; 23: 0.893, 0.031; 31: 0.901, 0.031; 42: 0.932,
# 0.028, the lowest shapes browDown_L on 11 (0.42; 0.56-0.60 on 23 and 31) and mouthFrown_R
# (0.53-0.74). With one un-mixing penalty (0.1) at every turn: 0.916, 0.025; 0.913, 0.029; 0.915,
# 0.029; 0.946, 0.025 (browDown_L 0.45 on 11). With the map's 1,500 components: 0.894, 0.027;
# 0.876, 0.031; 0.903, 0.030; 0.933, 0.026,
# browDown_L on 11 and 23 0.27, 0.26. Before the map read the face's edges: 0.852, 0.033; 0.808,
# 0.039; 0.841, 0.035; 0.885, 0.033, the frowns 0.01-0.62 and browDown_L 0.44-0.77 the lowest
# (before the un-mixing: 0.845, 0.040; 0.797, 0.048; 0.826, 0.043; 0.877, 0.040; with its penalty at
# 0.03, not chosen: 0.887, 0.833, 0.865, 0.915; before the map read the points' weights too: 0.816,
# 0.044; 0.787, 0.050; 0.810, 0.047; 0.858, 0.044).
MEASURED_UNSEEN_IDENTITIES = {11: (0.88, 0.030), 23: (0.87, 0.034), 31: (0.88, 0.034),
                              42: (0.91, 0.031)}


@pytest.mark.parametrize("identity", sorted(MEASURED_UNSEEN_IDENTITIES))
def test_weights_follow_unseen_identities_as_measured(identity, shared_data):
    take = rendered_take("moving", identity=identity)
    correlations, mae, text = _weight_figures(take, track_rendered(take))
    least_mean, most_mae = MEASURED_UNSEEN_IDENTITIES[identity]
    assert correlations.mean() >= least_mean and mae <= most_mae, f"MAE {mae:.3f}; {text}"


def test_the_faces_image_reads_what_the_points_miss(moving):
    """The same take without the appearance: the points and the eyes alone read it worse."""
    take, tracked = moving
    with_appearance = _weight_figures(take, tracked)[0].mean()
    without = _weight_figures(take, track_rendered(take, appearance=False))[0].mean()
    assert without >= MEASURED_WITHOUT_APPEARANCE
    assert with_appearance >= without + 0.15, (with_appearance, without)


@pytest.mark.parametrize("take_name", sorted(MEASURED_POSE))
def test_head_rotation_as_measured(take_name, request):
    assert_pose_as_measured(*request.getfixturevalue(take_name), *MEASURED_POSE[take_name],
                            SLOPE_RANGE)


@pytest.mark.parametrize("take_name", [
    "moving", "other_identity",
    pytest.param("moving_webcam", marks=pytest.mark.xfail(strict=True, reason=(
        "measured through a webcam: mean 0.929, MAE 0.029, but mouthFrown_R 0.69 (0.46 before "
        "the appearance's grid read a smoothed image and its weights were filtered over time)"))),
    pytest.param("moving_side_light", marks=pytest.mark.xfail(strict=True, reason=(
        "measured lit from one side: mean 0.841, MAE 0.040, mouthStretch_L 0.44, mouthFrown_R "
        "0.50: the appearance map learnt only faces lit from the camera's side")))])
def test_weights_reach_the_target(take_name, request):
    """Measured: mean correlation 0.963, MAE 0.021, every shape at least 0.86 (mouthFrown_R);
    identity 7: 0.937, 0.026, at least 0.71 (mouthStretch_R). With the appearance map's 1,500
    components: 0.948, 0.024, 0.81; identity 7 0.928, 0.027, 0.697, short of the target by one
    shape. Before the appearance map read the face's edges: 0.902, 0.031, the frowns 0.70 and 0.39.
    Without the face's appearance: 0.654, shapes below 0.8: frowns 0.23, 0.29, pucker 0.35,
    browOuterUp 0.50, 0.51, cheekPuff 0.56, browDown_R 0.61, noseSneer_R 0.65, smile_R 0.67,
    noseSneer_L 0.73, jawOpen 0.79; MAE 0.051: FaceMesh's points follow the frowns, brows,
    sneers, pucker and stretch by 0.3-0.45 of the true image motion with the head still,
    0.15-0.3 turned (the true points keep every shape: 0.95,
    test_the_true_points_keep_every_driven_shape)."""
    correlations, mae, text = _weight_figures(*request.getfixturevalue(take_name))
    assert correlations.mean() >= 0.85 and correlations.min() >= 0.7 and mae <= 0.08, text


# The known answer past the image models (helpers.takes.track_true_points: the take's own head
# sampled at the tracker's points and projected, through the same session onto the same head).
# Measured (mean correlation, least, MAE): the head still 0.973, 0.91 (mouthFrown_R), 0.019; the
# head moving, the tracker's points not sliding with the turn (the true points do not; FaceMesh's
# do): 0.951, 0.78 (mouthFrown_R), 0.027; identity 7 0.936, 0.79, 0.037 (with the slide learnt
# for FaceMesh's points the true points read 0.818 and 0.819, browOuterUp_L 0.21 and 0.20: the
# slide at a 16 deg pitch is read as a brow). The fit, the retargeting and the eyes' absence keep
# every driven shape: what the rendered takes lose is lost in FaceMesh's points.
KNOWN_ANSWER = {"still": (0.95, 0.85, 0.03), "moving": (0.93, 0.7, 0.04)}


@pytest.mark.parametrize("kind", sorted(KNOWN_ANSWER))
def test_the_true_points_keep_every_driven_shape(kind):
    tracker_model = load_tracker_model()
    if kind != "still":
        tracker_model = replace(tracker_model, shape_model=replace(tracker_model.shape_model,
                                                                   pose_offsets=None))
    take = rendered_take(kind)
    scores = unit_scores(take, track_true_points(take, tracker_model))
    correlations = np.array([c for c, _ in scores.values()])
    mae = np.mean([e for _, e in scores.values()])
    least_mean, least, most_mae = KNOWN_ANSWER[kind]
    text = ", ".join(f"{unit} {c:.2f}" for unit, (c, _) in scores.items())
    assert correlations.mean() >= least_mean and correlations.min() >= least and mae <= most_mae, (
        f"MAE {mae:.3f}; {text}")


# Measured on the turning take (a neutral face, its eyes fixed in the head, turning up to 30 deg):
# the largest weight of any key 0.30 (eyeLookIn_R, the gaze), of the eyes' keys 0.30: checked with a
# margin. Before a turned eye's lower lid counted far less than its upper lid
# (eyes.LOWER_LID_FACING_POWER 12, 4 before): 0.54 (eyeSquint_L), 0.54. With the material points'
# pull across the head's motion as large as along it (it is smaller since): 0.52 (eyeSquint_L; of
# the others 0.52, jawRight, the brows 0.45), of the eyes' keys 0.52 (eyeSquint_L); with only that
# smaller pull: 0.57 (browDown_L), 0.56. Before a pitched eye's lid rows counted less too
# (eyes.EyeGeometry.facing): 0.54 (eyeSquint_L), 0.54. Before the keys the eyes do not read were
# solved from the landmarks alone (core.session): 0.60 (browDown_L, answering the eye keys' motion
# about the eyes), the eyes' keys 0.54. Before the flow followed the frames less their blur (the
# pull 0.3 per pixel): 0.56 (browDown_L), 0.52. Before the material points' pull grew with the
# head's motion (a fixed 0.2): 0.58 (browDown_L; without the eyes' rows 0.51, jawRight), 0.52.
# Before the material points' refit carried a turn of their own and refined their depths
# (core.material_points): 0.64 (mouthLowerDown_L; without the eyes' rows 0.63), the eyes' keys 0.56
# (eyeSquint_L; the gaze keys 0.28 (eyeLookIn_R), eyeWide_R 0.29, eyeBlink_L 0.24). Before the eyes'
# frontal reading lost the slide learnt with the head's turn (core.eyes.EyeSlide) and a turned eye's
# lid rows counted less (eyes.UPPER_LID_FACING_POWER): 0.71 (eyeSquint_R), the gaze keys 0.48,
# eyeWide_R 0.45, eyeBlink_L 0.30.
MEASURED_FALSE_WEIGHT = {"": 0.34, "eye": 0.34}


@pytest.mark.parametrize("keys", sorted(MEASURED_FALSE_WEIGHT), ids=["all keys", "eye keys"])
def test_a_turning_neutral_face_as_measured(turning, keys):
    value, name = largest_false_weight(*turning, only=keys)
    assert value <= MEASURED_FALSE_WEIGHT[keys], f"{name} reached {value:.2f}"


# The same turning take after a wide calibration (three seconds of a neutral face turning over yaw
# +-30, pitch +-20 deg; the tracker unchanged: docs/method.md §11): 0.30 (eyeLookIn_R, an eye key;
# 0.55, eyeSquint_L, before the lower lid counted far less; 0.50 before the material points' pull
# across the head's motion was made smaller, 0.56 with that alone; 0.51 before a pitched eye's lid
# rows counted less too; the brows 0.38, 0.45 before the keys the eyes do not read were solved from
# the landmarks alone; 0.51 too before the flow followed the frames less their blur and before the
# pull grew with the head's motion), checked with a margin (before the material points' own turn and
# depths: 0.54 (mouthPress_L), the eyes' keys 0.52 (eyeSquint_L); before the eyes' learnt slide:
# 0.55, 0.52 (eyeSquint_R)).
MEASURED_FALSE_WEIGHT_WIDE = {"": 0.34, "eye": 0.34}


@pytest.mark.parametrize("keys", sorted(MEASURED_FALSE_WEIGHT_WIDE), ids=["all keys", "eye keys"])
def test_a_turning_neutral_face_after_a_wide_calibration_as_measured(turning_wide, keys):
    value, name = largest_false_weight(*turning_wide, only=keys)
    assert value <= MEASURED_FALSE_WEIGHT_WIDE[keys], f"{name} reached {value:.2f}"


# The keys the eyes do not read, on the turning take and after the wide calibration: 0.13
# (mouthStretch_L) and 0.12 (mouthStretch_L), the target, with the map's un-mixing penalty
# growing with the head's turn from its calibrated pose (0.05 at 6.5 deg to 0.3 at 31 deg); 0.23
# and 0.21 (mouthStretch_L, at yaw 26-30 deg) with one penalty (0.1) and the map's 2,500
# components (the cost of the map's finer reading; with 1,500: 0.19 and 0.19, mouthStretch_L, with
# the map reading the face's edges too); 0.21
# (browDown_R) and 0.20 (browDown_R) with the map's reading un-mixed (0.22 and 0.21 before it;
# 0.35 and 0.34 with the un-mixing's penalty at 0.03, which scales a misread up as it does an
# expression); 0.20 and 0.18 before the map read the points' weights; 0.21,
# mouthPress_L, and 0.20, mouthPress_R, with every key following its motion); 0.49
# (jawRight) and 0.54 (mouthStretch_R) without it.
@pytest.mark.parametrize("take_name", ["turning", "turning_wide"])
def test_a_turning_neutral_face_moves_the_keys_the_eyes_do_not_read_within_the_target(take_name,
                                                                                       request):
    value, name = largest_false_weight(*request.getfixturevalue(take_name), but="eye")
    assert value <= 0.15, f"{name} reached {value:.2f}"


@pytest.mark.xfail(strict=True, reason="measured: a neutral face turning up to 30 deg reaches "
                                       "weight 0.30 (eyeLookIn_R: the frontal iris still "
                                       "moves 0.053 eye widths per unit of the turn's "
                                       "direction, a slide of this head's own: the training "
                                       "heads' slopes spread by 0.07; the keys the eyes do "
                                       "not read 0.13, mouthStretch_L; FaceMesh's fit alone 0.55, "
                                       "browDown_L). With the true points' "
                                       "projections 0.04: FaceMesh's points slide as the head "
                                       "turns, and the learnt slide leaves 1.4 px median (a slide "
                                       "fitted to this head's own frames: 0.7)")
def test_a_turning_neutral_face_makes_no_expression(turning):
    value, name = largest_false_weight(*turning)
    assert value <= 0.15, f"{name} reached {value:.2f}"


def test_head_rotation_reaches_the_target(moving):
    """Measured: median 1.23 deg, max 2.61 deg, every axis within 0.01 of its scale (1.26, 2.59 with
    one un-mixing penalty at every turn; 1.22, 2.61 with
    the map reading the shading alone; before the map's reading was un-mixed 1.28, 2.77; without the
    appearance map's turn bias 1.32, 2.86; without the tracker model's learnt rotation bias
    either 1.45, 2.56; before the fit saw the modes as FaceMesh does and with the
    rotation's filter at 1 Hz: 1.57, 3.23)."""
    assert_pose_reaches_target(*moving)


@pytest.mark.xfail(strict=True, reason="measured: median 1.45 deg, max 3.30 deg, pitch at 1.04 of "
                                       "its scale (1.45, 3.28 with one un-mixing penalty at "
                                       "every turn; 1.48, 3.34 with the map reading the shading "
                                       "alone; 1.60, 3.64, 1.06 before the appearance map's "
                                       "turn bias; 1.54, 3.55 before its reading was un-mixed): "
                                       "the largest errors are a sneer's (frames 166-174, the "
                                       "head pitched 15-17 deg and turning 36 deg/s): pitch "
                                       "-2.9, yaw -1.5 deg; the same frames read -2.0 / -1.4 "
                                       "on the bundled head and -2.6 / -1.3 on identity 42, "
                                       "more than the biases learnt from other heads take off")
def test_head_rotation_of_another_identity_reaches_the_target(other_identity):
    assert_pose_reaches_target(*other_identity)
