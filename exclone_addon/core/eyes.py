"""Eyes from the iris model: each eye's lids and gaze, read from its points and turned into
targets of the weight solve (docs/method.md §10, §12).

A reading measures everything in the eye's own frame: the line through its two corners (x along
it, image-left to image-right; y up, perpendicular to it), in units of the corner distance, so
it does not change as the face moves in the image, nearer or farther or rolled. Per eye:
- the heights of the upper and lower lid above the corner line (the middle three points of each
  lid); their difference is the opening;
- the iris centre relative to the corners' midpoint.
Eye 0 is the image-left eye (the subject's right, ARKit's _R), eye 1 the image-right eye (_L).

A turned head's reading is first brought back to what the eyes would show facing the camera
(EyeGeometry, through the fitted head pose), less what the iris model's reading of a neutral
face's eyes still does with the head's turn (EyeSlide, learnt at build time from rendered heads
as the tracker model's points' slide is: core.tracker_model.learn_eye_slide).

Targets, relative to the actor's neutral reading (calibrated with the neutral face), against
ARKit's eye keys by name (an avatar without them gets no eye rows):
- lids: each lid's height change as a fraction of the neutral opening, against what each key
  does to it as the iris model reads it (LID_CHANGES): a blink mostly lowers the upper lid, a
  squint raises the lower one, wide raises the upper one;
- gaze: the iris's shift, as an angle of the eyeball (EYE_RADIUS_WIDTHS), the same for both
  eyes (conjugate_gaze), against the eyeLook keys: yaw = Out - In for the left eye (In - Out
  for the right), pitch = Up - Down, at EYE_LOOK_FULL_DEG for a weight of 1, and each pair's
  sum at the turn's size (an eye does not look in and out at once). While the eyes are closing
  their irises are not read: the gaze holds the last open reading, so a blink is never read as
  looking down.
Each target row weighs EYE_TRUST times a typical key's landmark evidence: what the iris model
reads of the eyes overrules what the face's landmarks suggest there.
"""
from dataclasses import dataclass

import numpy as np

from .tracking import FRONTAL, ShapeModel

# Image pixels (y down) -> the readings' axes (y up).
_Y_UP = np.array([1.0, -1.0])
# The iris model's contour ids (face_models.EyeLandmarks): corners and the middle of each lid.
OUTER, INNER = 0, 8
LOWER_LID = (3, 4, 5)
UPPER_LID = (11, 12, 13)
# (x, y) -> (-y, x): a quarter turn, from an eye's x axis to its y axis.
_QUARTER_TURN = np.array([-1.0, 1.0])
# ARKit's suffix of each eye in the reading's order.
SIDES = ("_R", "_L")
# The iris centre's distance from the eyeball's centre of rotation in eye widths (corner to
# corner): about 10 mm over 29 mm in an adult eye.
EYE_RADIUS_WIDTHS = 0.35
# How far the iris centre (looking ahead) and the lids' middles are in front of the corners'
# midpoint, in eye widths: about 3 mm (the corners are set back, the outer one most), so the
# centre of rotation is 0.25 widths behind the corners. Measured: a head turned by 30 degrees
# shifts the iris by about 0.06 widths against the corners (rendered ICT head, iris model).
IRIS_DEPTH_WIDTHS = 0.1
# The eye turn an ARKit eyeLook weight of 1 stands for.
EYE_LOOK_FULL_DEG = 30.0
# What each ARKit eye key at 1 does to the lids as the iris model reads them: (key, change of the
# upper lid's height, of the lower lid's), in units of the neutral opening. A closed eye's
# contours keep about half the neutral gap, the upper lid coming most of the way (measured on
# rendered blinks: -0.45 and +0.1); the lids follow the eyes a little as they look up or down.
# eyeWide and eyeSquint move the lids less than these say (0.09-0.10 and 0.04-0.05, measured on
# the appearance map's training takes, against a frame's error of 0.03): the measured values
# read them at twice the gain but raise the largest false lid weight's 90th percentile there
# 0.27 -> 0.40, so these read them at a low gain (docs/method.md §10).
LID_CHANGES = (("eyeBlink", -0.45, 0.10), ("eyeWide", 0.30, 0.0), ("eyeSquint", 0.0, 0.25),
               ("eyeLookUp", 0.15, 0.0), ("eyeLookDown", -0.15, 0.0))
# A key that closes at least this share of an eye's opening on the avatar (retarget.
# eye_closures) is that eye's blink when the avatar has none of the ARKit keys for its lids (a
# character's own keys, VRM's Blink_L): its lid rows are eyeBlink's above times its closure.
# Keys that only narrow the eye (a squint, a frown pulling the lid) close far less of it.
CLOSING_SHARE = 0.5
# The eyes are closing when their mean opening is below this fraction of the neutral one: their
# irises are not read then. Both eyes are taken together: the first and last frames of a blink
# read about 0.6-0.75 (the closing lids hide the iris and the model guesses it), looking down
# by 20 degrees lowers one eye's upper lid to about 0.8 but hardly the other's.
OPEN_FRACTION = 0.8
# How much a target row counts against the landmarks, per unit of a key's mean landmark norm.
EYE_TRUST = 30.0
# A turned or pitched eye's lid rows count less, by its facing (EyeReading.facing) to these
# powers: the iris model reads a foreshortened eye's lids worse (the far eye of a turned head,
# partly behind the nose; a pitched head's eyes along their lids, docs/method.md §10). The power
# 4 makes the weight about the square of the eye's width in the image against a frontal one's
# (as conjugate_gaze weighs the gaze): on the rendered turning take (the head up to 30 deg) the
# far eye's facing reads 0.78 where its width in the image is 0.69 of the frontal. There, after
# the learnt slide, the far eye's upper lid still read 0.13-0.16 of its opening high at 30 deg
# (eyeWide_L 0.40, answered by browDown_L 0.86); weighed with power 2: 0.75 (browDown_L), the
# eyes' keys 0.58; with 4: 0.64 (mouthLowerDown_L, not an eye's), 0.56.
UPPER_LID_FACING_POWER = 4
# The lower lid's row counts far less still: the iris model loses it first. On the appearance
# map's training takes (96 ICT heads, tracked as a camera's frames; frames without eye keys) its
# error against the head's own neutral grows from 0.031 of the opening (rms) facing the camera
# to 0.063 at facing 0.8-0.85 and 0.117 at 0.75-0.8, the upper lid's from 0.043 to 0.066 and
# 0.063; the errors last (frame-to-frame correlation 0.82) and a squint moves the lower lid
# little, so a turned eye's lower lid reads as a squint. There, on 32 of the takes, the
# squint's squared error with the lower lid's power at 4 / 8 / 12 / 16 / 24: 0.0197 / 0.0133 /
# 0.0091 / 0.0074 / 0.0061, falling as the squint is read less; the blinks and eyeWide unchanged,
# the squint's reading at its peaks facing the camera 0.20 / 0.20 / 0.20 / 0.19 / 0.18 of the
# truth: 12 halves the error and keeps the frontal squint as it was.
LOWER_LID_FACING_POWER = 12


@dataclass
class EyeReading:
    """One frame's measures of both eyes (eye widths; see the module's docstring)."""
    upper: np.ndarray     # (2,) upper-lid height above the corner line
    lower: np.ndarray     # (2,) lower-lid height (negative: below the line)
    iris: np.ndarray      # (2, 2) iris centre (x towards the image's right, y up)
    width: np.ndarray = None   # (2,) each eye's corner distance in the image, pixels
    # (2,) how squarely each eye faces the camera (EyeGeometry.facing; 1: as a frontal face's)
    facing: np.ndarray = None

    @property
    def opening(self):
        return self.upper - self.lower

    @classmethod
    def from_measures(cls, measures):
        """The reading of (2, READING_MEASURES) measures (reading_measures)."""
        measures = np.asarray(measures, dtype=np.float64)
        return cls(measures[:, 0], measures[:, 1], measures[:, 2:])


def _eye_frame(left_corner, right_corner):
    """(origin, x axis, y axis, width) of an eye from its corners (..., 2) in y-up coordinates
    (any leading axes: one eye or a batch)."""
    axis = right_corner - left_corner
    width = np.maximum(np.hypot(axis[..., 0], axis[..., 1]), 1e-12)
    x = axis / width[..., None]
    return (left_corner + right_corner) / 2.0, x, x[..., ::-1] * _QUARTER_TURN, width


def _measure(left_corner, right_corner, upper, lower, iris):
    """(upper-lid height, lower-lid height, iris centre (..., 2)) in the eye's frame from its
    corners (..., 2), lid points (..., m, 2) and iris centre (..., 2)."""
    origin, x, y, width = _eye_frame(left_corner, right_corner)
    heights = [np.einsum("...mi,...i->...m", points - origin[..., None, :], y).sum(axis=-1)
               / points.shape[-2] / width for points in (upper, lower)]
    offset = iris - origin
    centre = np.concatenate((np.einsum("...i,...i->...", offset, x)[..., None],
                             np.einsum("...i,...i->...", offset, y)[..., None]), axis=-1)
    return heights[0], heights[1], centre / width[..., None]


def read_eyes(eyes):
    """EyeReading from face_models.EyeLandmarks (image pixels, y down)."""
    flip = np.array([1.0, -1.0])
    contours = eyes.contours * flip
    # eye 0's outer corner is on the image's left, eye 1's on its right
    corners = contours[[[0], [1]], [[OUTER, INNER], [INNER, OUTER]]]
    upper, lower, iris = _measure(corners[:, 0], corners[:, 1], contours[:, list(UPPER_LID)],
                                  contours[:, list(LOWER_LID)], eyes.irises[:, 0] * flip)
    widths = np.linalg.norm(eyes.contours[:, OUTER] - eyes.contours[:, INNER], axis=1)
    return EyeReading(upper, lower, iris, widths)


# FaceMesh's corners of each eye in the reading's order (image-left corner, image-right corner).
FACEMESH_CORNERS = ((33, 133), (362, 263))
GEOMETRY_ITERATIONS = 3
# The measures of a frontal reading an EyeSlide moves, per eye: upper lid, lower lid, iris x, y.
READING_MEASURES = 4


def reading_measures(reading):
    """(2, READING_MEASURES) an EyeReading's measures per eye (EyeSlide's order)."""
    return np.column_stack((reading.upper, reading.lower, reading.iris))


@dataclass(frozen=True)
class EyeSlide:
    """How the frontal reading of a neutral face's eyes (EyeGeometry.frontal) still changes with
    the head's turn: the iris model reads the lids and the iris of a turned eye a little apart
    from where the geometry puts them (the lids' depth and curve, the nose hiding the far eye's
    inner corner). Offsets (F, 2, READING_MEASURES) linear in ShapeModel.pose_features of the
    direction from centre (3,) to the camera (model space), zero facing the camera."""
    offsets: np.ndarray
    centre: np.ndarray

    def at(self, rotation, translation):
        """(2, READING_MEASURES) the slide at a pose (model -> camera)."""
        to_camera = ShapeModel.camera_offsets(rotation, translation, self.centre)
        return np.tensordot(ShapeModel.pose_features(to_camera[None])[0], self.offsets, axes=1)


class EyeGeometry:
    """The actor's eyes in the head's frame, so that a reading of a turned head can be brought
    to what the eyes would show facing the camera (frontal): each eye is a frame on its two
    corners' midpoint (the head's axes, x the subject's left, y up, z forward, in units of the
    corner distance; the corners as they are, the outer one further back; docs/method.md §10),
    whose lids' middles and iris centre (looking ahead) sit IRIS_DEPTH_WIDTHS in front of the
    corners' midpoint, the iris turning on a sphere of radius EYE_RADIUS_WIDTHS. Uncorrected, a
    head turning shifts the iris against the corners (it is in front of them) and widens or
    narrows the lids' opening against the eye's width.

    neutral_shape: (468, 3) the actor's calibrated neutral (model space: +Y up, +Z forward);
    camera: core.tracking.Camera of the take; slide: the EyeSlide taken off a frontal reading
    (None: none).
    """

    def __init__(self, neutral_shape, camera, slide=None):
        shape = np.asarray(neutral_shape, dtype=np.float64)
        self.camera = camera
        self.slide = slide
        corners = shape[np.array(FACEMESH_CORNERS)]                 # (eye, corner, xyz)
        self._origins = corners.mean(axis=1)
        self._widths = np.linalg.norm(corners[:, 1] - corners[:, 0], axis=1)
        self._corners = (corners - self._origins[:, None]) / self._widths[:, None, None]

    def _image(self, k, points, matrix, translation):
        """(..., m, 2) eye k's eye-frame points (..., m, 3) in the image (y up) at a pose (model ->
        camera: rotation matrix, translation); k as in _reading_of."""
        origin, width = self._origins[k][..., None, :], self._widths[k][..., None, None]
        camera_points = (origin + width * points).reshape(-1, 3) @ matrix.T + translation
        return (self.camera.project(camera_points) * _Y_UP).reshape(points.shape[:-1] + (2,))

    def _reading_of(self, k, points, rotation, translation, corners=None):
        """Eye k's (upper, lower, iris x, iris y) (..., 4) as read_eyes would read the eye's
        corners and the eye-frame points (upper lid, lower lid, iris) (..., 3, 3) seen in this
        pose. k: 0 or 1, or an array of them shaped as points' leading axes (a batch of both
        eyes' points: all in one projection), or broadcasting to them. corners: the eyes'
        corners in the image (_image of self._corners[k]), the same for every point of a batch
        of one pose (None: projected here)."""
        points = np.asarray(points, dtype=np.float64)
        matrix = rotation.as_matrix()
        if corners is None:
            corners = self._image(k, self._corners[k], matrix, translation)
        image = self._image(k, points, matrix, translation)
        upper, lower, iris = _measure(corners[..., 0, :], corners[..., 1, :], image[..., 0:1, :],
                                      image[..., 1:2, :], image[..., 2, :])
        return np.concatenate((upper[..., None], lower[..., None], iris), axis=-1)

    @staticmethod
    def _points(upper, lower, iris):
        """The lids' middles and the iris centre (..., 3, 3) in eye units, for lid heights (...)
        and iris centres (..., 3)."""
        points = np.zeros(np.shape(upper) + (3, 3))
        points[..., 0, 1], points[..., 1, 1] = upper, lower
        points[..., :2, 2] = IRIS_DEPTH_WIDTHS
        points[..., 2, :] = iris
        return points

    def frontal(self, reading, rotation, translation, centres=None):
        """The EyeReading this pose's reading would be facing the camera: lid heights and the
        iris's frontal position in eye widths. centres (2, 2): each iris's centre of rotation
        (x, y; the calibrated neutral's iris); None while calibrating: the eyes are taken to
        look ahead and the centres are what is solved for. Both eyes are solved together."""
        r = EYE_RADIUS_WIDTHS
        measured = reading_measures(reading)      # (2, 4)
        # the eye-frame points of both eyes' unknowns p (2, B, 4)
        if centres is None:       # unknowns: lids and the centre (eyes ahead)
            def points(p):
                found = self._points(p[..., 0], p[..., 1], IRIS_DEPTH_WIDTHS)
                found[..., 2, :2] = p[..., 2:]
                return found
            start = measured
        else:                     # unknowns: lids and the iris's frontal offset
            centres = np.asarray(centres, dtype=np.float64)

            def points(p):
                x, y = np.moveaxis(np.clip(p[..., 2:] / r, -0.95, 0.95), -1, 0)
                found = self._points(p[..., 0], p[..., 1], IRIS_DEPTH_WIDTHS - r + r * np.sqrt(
                    np.maximum(1.0 - x * x - y * y, 0.05))[..., None])
                found[..., 2, :2] = centres[:, None] + p[..., 2:]
                return found
            start = np.column_stack((measured[:, :2], measured[:, 2:] - centres))
        eye = np.arange(2)[:, None]
        # the corners do not move with the unknowns: projected once
        corners = self._image(eye, self._corners[eye], rotation.as_matrix(), translation)
        p = _newton(lambda q: self._reading_of(eye, points(q), rotation, translation, corners)
                    - measured[:, None], start)
        found = np.column_stack((p[:, :2], p[:, 2:] if centres is None else centres + p[:, 2:]))
        if self.slide is not None:
            found = found - self.slide.at(rotation, translation)
        return EyeReading(found[:, 0], found[:, 1], found[:, 2:], reading.width,
                          self.facing(rotation))

    def facing(self, rotation):
        """(2,) each eye's corner line's length across the image at this head turn (model ->
        camera) over its length facing the camera (FRONTAL), at most 1, times the same of the
        lids' direction (the head's up axis less its part along the corner line): a turned
        head foreshortens the eye across, a pitched one along the lids."""
        axes = self._corners[:, 1] - self._corners[:, 0]
        up = np.array([0.0, 1.0, 0.0]) - axes[:, 1:2] * axes / (axes ** 2).sum(axis=1,
                                                                              keepdims=True)
        shares = []
        for directions in (axes, up):
            seen = np.linalg.norm(rotation.apply(directions)[:, :2], axis=1)
            frontal = np.linalg.norm(FRONTAL.apply(directions)[:, :2], axis=1)
            shares.append(np.minimum(seen / frontal, 1.0))
        return shares[0] * shares[1]


def _newton(residual, start, step=1e-4):
    """A few Newton steps on square residuals with forward-difference Jacobians, for several
    problems at once: start (P, n); residual takes points (P, B, n) to theirs (P, B, n), so each
    step evaluates every problem's point and its n forward steps in one call. A problem whose
    Jacobian is singular keeps its last point."""
    p = np.array(start, dtype=np.float64)
    steps = step * np.eye(p.shape[1])
    going = np.ones(len(p), dtype=bool)
    for _ in range(GEOMETRY_ITERATIONS):
        values = residual(np.concatenate((p[:, None], p[:, None] + steps), axis=1))
        r = values[:, 0]
        jacobians = np.swapaxes((values[:, 1:] - r[:, None]) / step, 1, 2)
        try:        # all problems' steps in one call, unless one of them is singular
            p[going] -= np.linalg.solve(jacobians[going], r[going][..., None])[..., 0]
            continue
        except np.linalg.LinAlgError:
            pass
        for k in np.flatnonzero(going):
            try:
                p[k] = p[k] - np.linalg.solve(jacobians[k], r[k])
            except np.linalg.LinAlgError:
                going[k] = False
    return p


def neutral_reading(readings):
    """The median of the calibration frames' readings."""
    return EyeReading(np.median([r.upper for r in readings], axis=0),
                      np.median([r.lower for r in readings], axis=0),
                      np.median([r.iris for r in readings], axis=0))


def gaze_degrees(reading, neutral):
    """(2, 2) each eye's (yaw, pitch) in degrees from its neutral: yaw towards the subject's
    left, pitch up."""
    shift = (reading.iris - neutral.iris) / EYE_RADIUS_WIDTHS
    return np.degrees(np.arcsin(np.clip(shift, -1.0, 1.0)))


def conjugate_gaze(reading, neutral):
    """(2, 2) both eyes' common (yaw, pitch): the eyes look the same way, and the eye seen
    wider counts more (by its squared width in the image: on a turned head the far eye is
    foreshortened and partly hidden by the nose, and its iris read worse)."""
    gaze = gaze_degrees(reading, neutral)
    weights = np.ones(2) if reading.width is None else reading.width ** 2
    common = weights @ gaze / weights.sum()
    return np.tile(common, (2, 1))


class EyeTargets:
    """The eyes' rows of the weight solve for an avatar's keys (names) and the actor's neutral
    eyes; key_scale: the mean squared landmark norm of a key in the solve (WeightSolver.scale).
    Rows exist for the ARKit keys the avatar has (eyeBlink, eyeWide, eyeSquint, eyeLook*), and
    for an eye with none of the lids' keys, for the keys that close it (closures (N, 2): each
    key's share of each eye's opening it closes on the avatar, retarget.eye_closures)."""

    def __init__(self, names, neutral, key_scale, closures=None):
        self.neutral = neutral
        self._row_weight = np.sqrt(EYE_TRUST * key_scale)
        self._rows = [_eye_rows(names, side, None if closures is None else closures[:, k])
                      for k, side in enumerate(SIDES)]
        # (N,) whether each key is one the rows read (the session solves the others without them)
        self.keys = np.zeros(len(names), dtype=bool)
        for row in (row for eye_rows in self._rows for row in eye_rows if row is not None):
            self.keys |= row != 0
        self._open_gaze = np.zeros((2, 2))

    def rows(self, reading):
        """(rows (k, N), targets (k,)) for one frame's EyeReading: rows @ weights ~ targets, a
        turned eye's lid rows weighed down (UPPER_ and LOWER_LID_FACING_POWER); None twice when
        the avatar has none of the keys."""
        opening0 = np.maximum(self.neutral.opening, 1e-12)
        upper = (reading.upper - self.neutral.upper) / opening0
        lower = (reading.lower - self.neutral.lower) / opening0
        if np.mean(reading.opening / opening0) > OPEN_FRACTION:
            self._open_gaze = conjugate_gaze(reading, self.neutral)
        facing = np.ones(2) if reading.facing is None else reading.facing
        rows, targets = [], []
        for k, eye_rows in enumerate(self._rows):
            yaw, pitch = self._open_gaze[k] / EYE_LOOK_FULL_DEG
            values = (upper[k], lower[k], yaw, pitch, abs(yaw), abs(pitch))
            trust = (facing[k] ** UPPER_LID_FACING_POWER, facing[k] ** LOWER_LID_FACING_POWER,
                     1.0, 1.0, 1.0, 1.0)
            for row, value, weight in zip(eye_rows, values, trust):
                if row is not None:
                    rows.append(weight * row)
                    targets.append(weight * value)
        if not rows:
            return None, None
        return self._row_weight * np.array(rows), self._row_weight * np.array(targets)


def _eye_rows(names, side, closures=None):
    """(upper-lid row, lower-lid row, yaw row, pitch row, yaw's size row, pitch's size row) of
    one eye over the keys, each (N,) or None when the avatar lacks all of its keys (LID_CHANGES;
    yaw towards the subject's left: the left eye looks out, the right one in; pitch up). The
    size rows hold each pair's sum to the turn's size, as ARKit's keys read (an eye does not
    look in and out at once): a pair whose keys move the face's points about alike and
    opposite (a character's cloned eyeLook keys: their sum moves them by a fifth of either)
    would otherwise rise together, unseen by the turn's row, to follow the points' noise.
    Without the lids' ARKit keys, the lid rows are the closing keys' (closures (N,), this eye's:
    CLOSING_SHARE)."""
    index = {name: j for j, name in enumerate(names)}

    def row(coefficients):
        present = {name + side: c for name, c in coefficients if name + side in index and c}
        if not present:
            return None
        values = np.zeros(len(names))
        for name, c in present.items():
            values[index[name]] = c
        return values

    outwards, inwards = ("eyeLookOut", "eyeLookIn") if side == "_L" else ("eyeLookIn", "eyeLookOut")
    upper, lower = (row([(key, up) for key, up, _ in LID_CHANGES]),
                    row([(key, down) for key, _, down in LID_CHANGES]))
    if upper is None and lower is None and closures is not None:
        closing = np.where(np.nan_to_num(closures) >= CLOSING_SHARE, closures, 0.0)
        if closing.any():
            blink_up, blink_down = next(change[1:] for change in LID_CHANGES
                                        if change[0] == "eyeBlink")
            upper, lower = blink_up * closing, blink_down * closing
    return (upper, lower,
            row([(outwards, 1.0), (inwards, -1.0)]),
            row([("eyeLookUp", 1.0), ("eyeLookDown", -1.0)]),
            row([(outwards, 1.0), (inwards, 1.0)]),
            row([("eyeLookUp", 1.0), ("eyeLookDown", 1.0)]))
