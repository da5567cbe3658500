"""Blinks and gaze through the image models: an ICT-topology head (the bundled one and an ICT
identity) rendered in background Blender blinking (150 ms blinks among them) and looking about
with known eye turns up to 20 degrees, facing the camera and turning (up to 25 degrees of yaw;
blender_tests/helpers/eye_takes.py), tracked by FaceTrackingSession.step as a camera's frames
are, onto the same head (so the ideal answer is the truth)."""
import cv2
import numpy as np
import pytest

from exclone_addon.core.retarget import AvatarRig
from exclone_addon.core.session import FaceTrackingSession
from exclone_addon.core.tracker_model import read_tracker_locations
from blender_tests.helpers.eye_takes import BLINKS, CALIBRATION_FRAMES, FPS, rendered_eye_take
from blender_tests.helpers.takes import OTHER_IDENTITY, through_a_webcam

# Each take by the name its measured figures are kept under: (turning, identity, whether its
# frames come as a webcam would deliver them: takes.through_a_webcam).
TAKES = {"facing": (False, None, False), "turning": (True, None, False),
         "facing_other_identity": (False, OTHER_IDENTITY, False),
         "turning_other_identity": (True, OTHER_IDENTITY, False),
         "facing_webcam": (False, None, True), "turning_webcam": (True, None, True)}


@pytest.fixture(scope="module", params=sorted(TAKES))
def tracked_eyes(request):
    turning, identity, webcam = TAKES[request.param]
    if identity is not None:
        request.getfixturevalue("shared_data")     # skips where the identity model is absent
    take = rendered_eye_take(turning=turning, identity=identity)
    if webcam:
        take = through_a_webcam(take)
    avatar = AvatarRig.from_locations(take.vertices, take.deltas, take.names,
                                      read_tracker_locations())
    session = FaceTrackingSession(avatar=avatar, camera=take.camera,
                                  calibration_frames=CALIBRATION_FRAMES)
    weights = {name: np.full(len(take.frames), np.nan) for name in take.names}
    for k, path in enumerate(take.frames):
        result = session.step(cv2.imread(str(path)), k / FPS)
        assert result.found, f"no face in frame {k}"
        if result.weights is not None:
            for name, value in result.weights.items():
                weights[name][k] = value
    w = weights
    yaw = w["eyeLookOut_L"] + w["eyeLookIn_R"] - w["eyeLookIn_L"] - w["eyeLookOut_R"]
    pitch = w["eyeLookUp_L"] + w["eyeLookUp_R"] - w["eyeLookDown_L"] - w["eyeLookDown_R"]
    return request.param, take, weights, yaw, pitch


def blink_frames(start, length):
    return slice(start, start + length)


# The weakest blink's peak (the lower eye's) in each take, measured, checked with a margin:
# facing the camera 0.733 (bundled head) and 0.81 (identity 7), turning 0.562 and 0.41; the
# bundled head through a webcam (takes.through_a_webcam) 0.638 and 0.705.
MEASURED_WEAKEST_BLINK = {"facing": 0.70, "turning": 0.52, "facing_other_identity": 0.75,
                          "turning_other_identity": 0.35, "facing_webcam": 0.60,
                          "turning_webcam": 0.66}
# The takes whose blinks fall short of the target, and why.
BLINKS_SHORT = {
    "turning_other_identity": "measured: two blinks read below 0.5 in the subject's right eye "
                              "(0.49 with the head pitched 12 deg down and the eyes looking 20 "
                              "deg down, 0.41 with the head turned 24 deg and pitched 15 deg "
                              "down): the iris model's contour of that closed eye keeps most of "
                              "its open height (the rendered lashes' dark line read as a narrow "
                              "eye). On four more ICT identities turning, the weakest blink "
                              "0.47-0.65 and the largest false blink 0.36-0.57; facing the "
                              "camera every blink is found on the three tried"}


def _blink_peaks(weights):
    """(blinks, 2) each blink's peak in eyeBlink_L and eyeBlink_R."""
    return np.array([[np.max(weights[name][blink_frames(start, length)])
                      for name in ("eyeBlink_L", "eyeBlink_R")] for start, length in BLINKS])


def test_every_blink_is_found_in_both_eyes_short_ones_included(tracked_eyes, request):
    name, take, weights, _, _ = tracked_eyes
    if name in BLINKS_SHORT:
        request.applymarker(pytest.mark.xfail(strict=True, reason=BLINKS_SHORT[name]))
    for (start, length), peaks in zip(BLINKS, _blink_peaks(weights)):
        assert peaks.min() > 0.5, f"the {length}-frame blink at frame {start} peaks at {peaks}"


def test_every_blink_is_read_as_measured(tracked_eyes):
    name, take, weights, _, _ = tracked_eyes
    weakest = _blink_peaks(weights).min()
    assert weakest >= MEASURED_WEAKEST_BLINK[name], f"the weakest blink peaks at {weakest:.2f}"


# The takes that read a blink where there is none, and why.
FALSE_BLINKS = {
    "turning_webcam": "measured: 0.505 (eyeBlink_L, frame 151) with the eyes looking 20 deg "
                      "down and 20 deg aside and the head pitched 14 deg down, through a "
                      "webcam's noise (0.425 there on the clean frames): the rendered lids stay "
                      "open while the eyes look down, and the iris model reads them closing"}


def test_no_false_blink(tracked_eyes, request):
    name, take, weights, _, _ = tracked_eyes
    if name in FALSE_BLINKS:
        request.applymarker(pytest.mark.xfail(strict=True, reason=FALSE_BLINKS[name]))
    open_eyes = take.blink == 0
    open_eyes[:CALIBRATION_FRAMES] = False
    for key in ("eyeBlink_L", "eyeBlink_R"):
        assert np.max(weights[key][open_eyes]) < 0.5


# The least correlation of the gaze's yaw and pitch with the truth: the target, 0.9, facing the
# camera (measured 0.988 and 0.974 on the bundled head, 0.989 and 0.980 on identity 7). With the
# head turning the pitch is short of it: measured 0.962 and 0.815 (identity 7: 0.955 and 0.742),
# checked with a margin; through a webcam 0.986 and 0.953 facing, 0.955 and 0.661 turning (the
# iris model's reading of a noisy eye). The pitch also reads at about half its size (0.034 per
# degree of the eyes' pitch where a full eyeLook pair gives 0.067; the yaw 0.061): the iris
# model's iris moves about half as far up and down as the geometry says, on six ICT heads
# (0.43-0.57 of the yaw's gain). Read at its full size, the turning neutral face's false gaze
# rises from 0.24-0.35 to 0.38-0.55 on four heads (eyeLookUp / Down) and the weakest blink here
# falls 0.56 -> 0.49: not done.
GAZE_CORRELATION = {"facing": (0.9, 0.9), "turning": (0.9, 0.75),
                    "facing_other_identity": (0.9, 0.9), "turning_other_identity": (0.9, 0.7),
                    "facing_webcam": (0.9, 0.9), "turning_webcam": (0.9, 0.62)}


def test_gaze_follows_the_eyes(tracked_eyes):
    """The ARKit reading yaw = Out_L + In_R - In_L - Out_R (and pitch = Up - Down) against the
    true eye turn over the frames with open eyes."""
    name, take, _, yaw, pitch = tracked_eyes
    frames = np.flatnonzero(take.blink == 0)
    frames = frames[frames >= CALIBRATION_FRAMES]
    least_yaw, least_pitch = GAZE_CORRELATION[name]
    assert np.corrcoef(yaw[frames], take.yaw[frames])[0, 1] >= least_yaw
    assert np.corrcoef(pitch[frames], take.pitch[frames])[0, 1] >= least_pitch


# Measured facing the camera: the keys the eyes do not read (the take moves only the eyes and lids)
# reach 0.21 (cheekRaiser_R in a blink); with the head turning 0.32; on identity 7 0.30 and 0.36;
# through a webcam (takes.through_a_webcam) 0.27 and 0.29. With the actor's neutral reading its
# calibration's mean (core.appearance.NeutralReading) 0.23, 0.34, identity 7 0.30 and 0.37, through
# the webcam 0.25 and 0.29. Without the appearance's weights filtered over time (core.session)
# 0.25, 0.36, 0.31, 0.38, 0.29, 0.33; before the image was also smoothed for the appearance's grid
# (core.appearance.GRID_ANTIALIAS; the map was learnt from unsmoothed grids) 0.20 (cheekSquint_L in
# a blink; browInnerUp_R 0.20 between blinks) and 0.31 (cheekRaiser_R, in a blink), identity 7 0.24
# and 0.31, through the webcam 0.23 and 0.33: the appearance map reads the closing lids' edges a
# little as a cheek's raise, and its un-mixing penalty is smaller near the calibrated pose than it
# was (0.05-0.1 below 16 deg; with one penalty, 0.1, at every turn: 0.17, browInnerUp_R, and 0.27;
# with its 1,500 components: 0.18 (cheekRaiser_R) in a blink, 0.29 turning). Before the map read
# the face's edges: 0.14 (cheekSquint_R) in the blinks, 0.07 between them, turning 0.20
# (browInnerUp_R) (0.17, cheekRaiser_R, and 0.09 before the appearance map's reading was un-mixed;
# 0.38 with the un-mixing's penalty at 0.03, not chosen; 0.24 and 0.19, the brows, before the map).
# Before those keys were solved from the landmarks alone, the eye keys' motion not taken off them
# (core.session): 0.66 (browOuterUp_R), 0.88 (browDown_L). Checked with a margin.
MEASURED_OTHER_KEYS = {"facing": 0.24, "turning": 0.35, "facing_other_identity": 0.33,
                       "turning_other_identity": 0.39, "facing_webcam": 0.29,
                       "turning_webcam": 0.32}


def test_blinks_and_gaze_move_no_other_key_as_measured(tracked_eyes):
    take_name, take, weights, _, _ = tracked_eyes
    others = {name: values[CALIBRATION_FRAMES:] for name, values in weights.items()
              if not name.startswith("eye")}
    name = max(others, key=lambda n: np.max(others[n]))
    most = MEASURED_OTHER_KEYS[take_name]
    assert np.max(others[name]) <= most, f"{name} reached {np.max(others[name]):.2f}"


def test_a_blink_is_not_read_as_looking_down(tracked_eyes):
    _, take, _, _, pitch = tracked_eyes
    for start, length in BLINKS:
        before = pitch[start - 1]
        during = pitch[blink_frames(start, length)]
        assert np.min(during) > before - 0.1, (start, before, during)
