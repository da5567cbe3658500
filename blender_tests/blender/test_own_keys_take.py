"""Tracking through the image models onto a character that carries its own keys: the MakeHuman
child (../shared/data/characters/mh_child_body_expr.blend) with MakeHuman's ten expression units
(eye closures, an open mouth, a smile, brows up and down, a pucker; no ARKit name among them),
rendered wearing them with known weights and a known head turn (helpers.character_takes.
rendered_own_keys_take), tracked frame by frame by FaceTrackingSession.step onto the same
character as a user's avatar, so the ideal answer is the truth. Nothing here is ARKit: the eyes'
reading reaches the keys through what they do to the avatar's lids (retarget.eye_closures,
eyes.EyeTargets), the rest through the points and the appearance map's motion. Figures
measured, checked with a margin; the issue's targets as strict expected failures where they are
not met."""
import bpy
import numpy as np
import pytest

from exclone_addon.core import capture
from blender_tests.helpers.animation import keyframes
from blender_tests.helpers.character_files import load_into_scene
from blender_tests.helpers.character_takes import (OWN_KEYS_CHARACTER, own_keys_character,
                                                   rendered_own_keys_take, tracked_take_fixtures)
from blender_tests.helpers.takes import (assert_pose_as_measured, assert_pose_reaches_target,
                                         largest_false_weight)

CLOSING = ("eye-right-closure", "eye-left-closure")     # the subject's right eye, then the left
moving, still, turning = tracked_take_fixtures(rendered_own_keys_take)


def test_the_characters_closing_keys_are_measured(shared_data):
    """Each eye closure closes its own eye on the body (the lids found as Clone finds them) and
    nothing else closes either: measured 1.15 and 1.12, the others within 0.01."""
    rig = own_keys_character().rig
    closures = rig.closures
    for eye, name in enumerate(CLOSING):
        j = rig.names.index(name)
        assert closures[j, eye] > 0.9 and abs(closures[j, 1 - eye]) < 0.05, closures[j]
    others = [j for j, name in enumerate(rig.names) if name not in CLOSING]
    assert np.all(np.abs(closures[others]) < 0.1), closures[others]


def test_drive_from_webcam_blinks_the_characters_own_keys(shared_data, tmp_path):
    """The add-on's path: the still take's frames as an image folder, Drive from Webcam onto the
    child's Body (every key) recording keyframes. Each eye closure is keyed above 0.5 at each of
    its bumps and below it wherever it is zero (the closures measured by the add-on's rig)."""
    take = rendered_own_keys_take("still")
    folder = tmp_path / "frames"
    folder.mkdir()
    for k, path in enumerate(take.frames):
        (folder / f"{k:04d}.png").symlink_to(path)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    body = load_into_scene(shared_data / "characters" / OWN_KEYS_CHARACTER)["Body"]
    bpy.context.view_layer.objects.active = body
    assert bpy.ops.exclone.drive_from_webcam(source_type='FOLDER', filepath=str(folder),
                                             record=True) == {'FINISHED'}
    keyed = keyframes(body.data.shape_keys)
    fps = bpy.context.scene.render.fps
    for name in CLOSING:
        values = dict(keyed[f'key_blocks["{name}"].value'])
        truth = take.truth[:, take.names.index(name)]
        # each image's key (the calibration's images have none: NaN)
        at = np.array([values.get(1 + round(k / capture.FOLDER_FRAME_RATE * fps), np.nan)
                       for k in range(len(truth))])
        assert np.all(np.isfinite(at[take.calibration_frames:]))
        for first, stop in _bumps(truth):
            assert at[first:stop].max() > 0.5, (name, first, at[first:stop])
        assert np.nanmax(at[truth == 0]) < 0.5, name


def _after_calibration(take, tracked):
    frames = slice(take.calibration_frames, None)
    return take.truth[frames], tracked.weights[frames]


def _bumps(truth):
    """[(first, stop)] of each run of frames where `truth` (T,) is above zero."""
    edges = np.diff(np.concatenate(([0], (truth > 0).astype(int), [0])))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)))


@pytest.mark.parametrize("take_name", ["moving", "still"])
def test_every_closure_is_found_and_none_is_false(take_name, request):
    """Each eye closure's every bump reads above 0.5 at its peak (measured 1.00: the closed eyes
    read beyond eyeBlink's reading, at 1.2-1.4 times the truth), and no frame where it is zero
    reads above 0.5 (measured: moving 0.38 and 0.45, with the head pitched down; still 0.09).
    Before the closures were measured, neither key ever rose above 0.01."""
    take, tracked = request.getfixturevalue(take_name)
    truth, weights = _after_calibration(take, tracked)
    for name in CLOSING:
        j = take.names.index(name)
        for first, stop in _bumps(truth[:, j]):
            assert np.nanmax(weights[first:stop, j]) > 0.5, (name, first, weights[first:stop, j])
        assert np.nanmax(weights[truth[:, j] == 0, j]) < 0.5, name


def _figures(take, tracked):
    """Per key (correlation, mean absolute error, gain: the slope of the weight on the truth)."""
    truth, weights = _after_calibration(take, tracked)
    seen = np.all(np.isfinite(weights), axis=1)
    truth, weights = truth[seen], weights[seen]
    return {name: (np.corrcoef(weights[:, j], truth[:, j])[0, 1],
                   np.abs(weights[:, j] - truth[:, j]).mean(),
                   np.polyfit(truth[:, j], weights[:, j], 1)[0])
            for j, name in enumerate(take.names)}


def _text(figures):
    return ", ".join(f"{name} {c:.2f} (gain {g:.2f})" for name, (c, _, g) in figures.items())


# Measured (mean correlation over the ten keys, MAE, the median gain): the head moving 0.846,
# 0.073, 0.30 (the lowest eyebrows-left-up 0.72; the open mouth at a gain of 0.21); still 0.938,
# 0.051, 0.44 (the lowest the frown 0.80). Before the actor's neutral reading followed the head's
# turn (core.appearance.NeutralReading): 0.823 (eyebrows-left-up 0.66) and 0.940; before the
# appearance's grid read a smoothed image and its weights were filtered over time (stop 39):
# 0.820 and 0.935. With the appearance
# map's motion at its learnt
# share (1, before appearance.MOTION_SHARE) 0.741 and 0.888. Besides the eyes and the smile the
# keys read at a tenth to a third of their size: the appearance map, learnt on ICT heads, reads
# this face's open mouth and frown as little of ICT's.
MEASURED_WEIGHTS = {"moving": (0.82, 0.078, 0.26), "still": (0.91, 0.055, 0.40)}


@pytest.mark.parametrize("take_name", sorted(MEASURED_WEIGHTS))
def test_own_keys_follow_the_face_as_measured(take_name, request):
    figures = _figures(*request.getfixturevalue(take_name))
    correlations, errors, gains = np.array(list(figures.values())).T
    least_mean, most_mae, least_gain = MEASURED_WEIGHTS[take_name]
    assert correlations.mean() >= least_mean and errors.mean() <= most_mae, _text(figures)
    assert np.median(gains) >= least_gain, _text(figures)


def test_own_keys_reach_the_target_with_the_head_still(still):
    """The issue's figures with the head still (though most keys read at a fraction of their
    size: see MEASURED_WEIGHTS)."""
    figures = _figures(*still)
    correlations, errors, _ = np.array(list(figures.values())).T
    assert correlations.mean() >= 0.85 and correlations.min() >= 0.7 and errors.mean() <= 0.08, \
        _text(figures)


@pytest.mark.xfail(strict=True, reason="measured: 0.846 with the head moving (every key at "
                                       "0.72 or more), MAE 0.073: the mean 0.004 short")
def test_own_keys_reach_the_target_with_the_head_moving(moving):
    figures = _figures(*moving)
    correlations, errors, _ = np.array(list(figures.values())).T
    assert correlations.mean() >= 0.85 and correlations.min() >= 0.7 and errors.mean() <= 0.08, \
        _text(figures)


# Measured (median, max rotation error in degrees; slopes pitch, yaw): moving 5.09, 10.16 (1.29,
# 1.19); the neutral face turning 5.10, 10.67 (1.23, 1.17). The turn reads a fifth to a quarter
# too large: this face's proportions are a child's, further from the ICT heads the tracker
# model was learnt from than the MakeHuman man's (test_character_take: 1.11, 1.12).
MEASURED_POSE = {"moving": (5.4, 10.8), "turning": (5.4, 11.2)}
SLOPE_RANGE = (0.95, 1.35)


@pytest.mark.parametrize("take_name", sorted(MEASURED_POSE))
def test_head_rotation_as_measured(take_name, request):
    assert_pose_as_measured(*request.getfixturevalue(take_name), *MEASURED_POSE[take_name],
                            SLOPE_RANGE)


@pytest.mark.xfail(strict=True, reason="measured: median 5.09 deg, max 10.16 deg, pitch and yaw "
                                       "at 1.29 and 1.19 of their size (see MEASURED_POSE)")
def test_head_rotation_reaches_the_target(moving):
    assert_pose_reaches_target(*moving)


# Measured on the neutral face turning up to 30 deg: the closures 0.51 (the head pitched down
# by 10-20 deg: both eyes read as half closed, 0.3-0.4 for a second and more), the other keys
# 0.21 (eyebrows-right-up; 0.24 before stop 39's filter). Checked with a margin.
MEASURED_FALSE_WEIGHT = {"eye": 0.56, "others": 0.25}


def test_a_turning_neutral_face_as_measured(turning):
    found = {"eye": largest_false_weight(*turning, only="eye"),
             "others": largest_false_weight(*turning, but="eye")}
    assert all(found[keys][0] <= most for keys, most in MEASURED_FALSE_WEIGHT.items()), found


@pytest.mark.xfail(strict=True, reason="measured: 0.51 (eye-right-closure, the head pitched "
                                       "down), the other keys 0.21")
def test_a_turning_neutral_face_makes_no_expression(turning):
    assert largest_false_weight(*turning)[0] <= 0.15
