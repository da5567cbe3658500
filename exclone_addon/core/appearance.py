"""What the face's own image says of its expression (docs/method.md §12).

FaceMesh's points follow the frowns, brows, pucker and cheeks by a few pixels at most, about its
own jitter; the shading and the painted edges of the face move plainly. So each frame the face is
frontalised: a fixed grid over the tracker model's mean face seen from the front, each grid pixel
taken from the image, smoothed at the grid's scale, where the actor's calibrated neutral, posed as
tracked, puts it (a piecewise-affine warp over the points' Delaunay triangles). The expression
moves the face within that grid; the head's turn does not move it. It is read twice, each over the
face's median brightness: its shading (the grid averaged over 2x2 pixels) and its edges (histograms
of the gradients' directions over cells of the grid, HOG: a light falling differently on a turned
face changes them less than the shading, and an edge moving within a cell changes them as a shade
does not). Less the actor's own neutral face's reading (NeutralReading: a line in the head's turn
through the calibration frames'), both are read by a linear map learnt at build time from rendered
takes of ICT identities (scripts/make_appearance_model.py) into the library's keys the eyes do not
read. Beside the image the map reads the same keys' weights as the points' expression gives them
(solved against the keys' motion at the tracker's points): what the points do see well (an open
jaw, a smile) tells the map what the image's change is not (a jaw's opening pulls the mouth's
corners down as a frown does).

A linear map learnt by ridge regression reads each key at a fraction of its weight and leaks
some of the others' into it (on frames it was not learnt from, a frown at 0.15-0.16 of its
weight, the mouth's stretch and an open jaw at about a third of that). That response is learnt
too (learn_response: what the map reads per unit of each key, on frames of takes it was not
learnt from), and the weights shown are the ones in [0, 1] whose response best explains what
the map read: a bounded least squares, with a penalty on the weights (unmixed_weights). The
penalty grows with the head's turn from the pose it was calibrated in
(AppearanceMap.unmixing_ridge): the further the face turns from there, the further a neutral
face's reading strays from its calibrated one, and a larger penalty keeps that stray reading
from being un-mixed into keys.

The same keys' weights say how the fit misreads the head's turn: FaceMesh's points move with a
sneer or a pucker in ways the shape model partly explains as a pitch or a yaw. What remains of
that after the tracker model's own learnt bias is learnt as linear in the map's weights
(learn_turn_bias) and taken off the tracked turn.
"""
from dataclasses import dataclass
from functools import cached_property, lru_cache

import cv2
import numpy as np
from scipy.spatial import Delaunay
from scipy.spatial.transform import Rotation

from . import data
from .library import ARKIT_SPLIT
from .retarget import WeightSolver, bounded_weights
from .tracking import FRONTAL

FRONTAL_SIZE = (80, 96)       # the frontal grid (width, height), the face's width 76 pixels
SHADING_SIZE = (40, 48)       # the shading read: the grid averaged over 2x2 pixels
SHADING_FEATURES = SHADING_SIZE[0] * SHADING_SIZE[1]
# The edges read: HOG over cells of 8x8 grid pixels in blocks of 2x2 cells (each block's
# histograms normalised together), 9 directions. On the appearance map's training takes (a map
# learnt without each quarter of them, 1,500 components) the edges beside the shading raised the
# held-out correlation over the keys from 0.405 to 0.495, the frowns' from 0.24-0.26 to
# 0.36-0.38 (docs/method.md §12).
GRADIENT_CELL = 8
GRADIENT_BINS = 9


def gradient_descriptor():
    """The HOG that reads the grid's edges (its blocks step by one cell)."""
    cell = (GRADIENT_CELL, GRADIENT_CELL)
    return cv2.HOGDescriptor(FRONTAL_SIZE, (2 * GRADIENT_CELL,) * 2, cell, cell, GRADIENT_BINS)


GRADIENT_FEATURES = gradient_descriptor().getDescriptorSize()
FEATURES = SHADING_FEATURES + GRADIENT_FEATURES
# The grid reads one image pixel in about 2.6 (a face 200 pixels wide): sampled alone, each read
# pixel would carry its own sensor noise whole into the reading. So the image is smoothed first,
# as wide as averaging each grid pixel's footprint would (a box s pixels wide has a standard
# deviation of s / sqrt(12), about 0.29 s): on the bundled head's moving take with a webcam's
# noise (standard deviation 6 / 10 of 255) the mean correlation 0.910 -> 0.929 / 0.858 -> 0.908
# (docs/method.md §12).
GRID_ANTIALIAS = 0.3
# The grid's median brightness before its edges are read (8-bit, as HOG takes them).
GRADIENT_BRIGHTNESS = 100.0
# 2: the turn's bias (turn_bias); 3: the points' weights read too; 4: the map's response;
# 5: the edges read beside the shading; 6: the un-mixing's penalty by the head's turn
MAP_VERSION = 6
REMEDY = "run scripts/make_appearance_model.py"
# learn_response's penalty per frame: only keeps a key the frames never move determined
RESPONSE_RIDGE = 1e-4


def antialiased_region(image, low, high, scale):
    """(region, corner): the part of `image` around the box from `low` to `high` (x, y pixels),
    smoothed for reading `scale` times smaller (GRID_ANTIALIAS; not when scale <= 1), and the
    region's top-left pixel (x, y) in the image."""
    sigma = GRID_ANTIALIAS * scale if scale > 1.0 else 0.0
    height, width = image.shape[:2]
    margin = 3.0 * sigma + 2.0
    x0, y0 = np.clip(np.floor(np.asarray(low) - margin).astype(int), 0, (width - 1, height - 1))
    x1, y1 = np.clip(np.ceil(np.asarray(high) + margin).astype(int) + 1, (x0 + 1, y0 + 1),
                     (width, height))
    region = image[y0:y1, x0:x1]
    if sigma > 0.0:
        region = cv2.GaussianBlur(region, (0, 0), sigma)
    return region, np.array([x0, y0], dtype=np.float64)


class FaceFrontaliser:
    """Warps a face in an image onto the frontal grid (FRONTAL_SIZE) from its points posed in
    the image: mean_points (n, 3) in the model's axes fix where each point lies on the grid."""

    def __init__(self, mean_points):
        width, height = FRONTAL_SIZE
        seen = FRONTAL.apply(mean_points - mean_points.mean(axis=0))[:, :2]
        low, high = seen.min(axis=0), seen.max(axis=0)
        self.grid_points = (seen - low) * ((width - 4) / (high[0] - low[0])) + 2.0   # (n, 2)
        triangulation = Delaunay(self.grid_points)
        rows, columns = np.mgrid[0:height, 0:width]
        pixels = np.column_stack((columns.ravel(), rows.ravel())).astype(np.float64)
        simplex = triangulation.find_simplex(pixels)
        self.inside = simplex >= 0
        affine = triangulation.transform[simplex[self.inside]]
        first_two = np.einsum("nij,nj->ni", affine[:, :2], pixels[self.inside] - affine[:, 2])
        self._bary = np.column_stack((first_two, 1.0 - first_two.sum(axis=1)))
        self._corners = triangulation.simplices[simplex[self.inside]]
        self._maps = np.full((len(pixels), 2), -1.0, dtype=np.float32)   # outside: no pixel
        small = cv2.resize(self.inside.reshape(height, width).astype(np.float32), SHADING_SIZE,
                           interpolation=cv2.INTER_AREA)
        self._shading_mask = (small > 0.999).ravel()    # cells wholly on the face
        self._gradients = gradient_descriptor()

    def frontal(self, gray, image_points):
        """The face on the grid (height, width) float32; image_points (n, 2): the points posed
        in `gray`'s pixels."""
        width, height = FRONTAL_SIZE
        scale = np.ptp(image_points[:, 0]) / np.ptp(self.grid_points[:, 0])
        region, corner = antialiased_region(gray, image_points.min(axis=0),
                                            image_points.max(axis=0), scale)
        self._maps[self.inside] = np.einsum("nk,nkd->nd", self._bary,
                                            image_points[self._corners] - corner)
        return cv2.remap(region, self._maps[:, 0].reshape(height, width),
                         self._maps[:, 1].reshape(height, width), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)

    def reading(self, gray, image_points):
        """(FEATURES,) the face on the grid, over its median brightness (a brighter light or
        skin reads the same): its shading at SHADING_SIZE (nought off the face), then its
        edges (GRADIENT_FEATURES)."""
        frontal = self.frontal(gray, image_points).astype(np.float32)
        face = cv2.resize(frontal, SHADING_SIZE, interpolation=cv2.INTER_AREA).ravel()
        on_face = face[self._shading_mask]
        brightness = max(float(np.median(on_face)), 1.0)
        reading = np.zeros(FEATURES)
        reading[:SHADING_FEATURES][self._shading_mask] = on_face / brightness
        levels = np.clip(frontal * (GRADIENT_BRIGHTNESS / brightness), 0.0, 255.0)
        reading[SHADING_FEATURES:] = self._gradients.compute(levels.astype(np.uint8)).ravel()
        return reading


@dataclass(frozen=True)
class NeutralReading:
    """The actor's neutral face's reading (FEATURES,) as the head turns: a line in the turn's
    pitch and yaw (camera axes, radians from the calibrated pose) through the calibration
    frames' readings. A face lit from one side, or shaped unlike the map's training heads, reads
    differently turned even at rest; the calibration sees how, for this actor under this light.
    The turn is held within what the calibration saw: a line through a second's turning is not
    trusted beyond it (extrapolated, the moving take read 0.943 against 0.952)."""
    mean: np.ndarray           # (FEATURES,) at the calibration's mean turn
    slope: np.ndarray          # (2, FEATURES) per radian of pitch and yaw
    mean_turn: np.ndarray      # (2,)
    least_turn: np.ndarray     # (2,) the calibration's range
    most_turn: np.ndarray
    reference: Rotation        # the calibrated pose (model -> camera)

    @classmethod
    def fitted(cls, readings, rotations, reference):
        """From the calibration frames' readings (F, FEATURES) and their head poses (a Rotation
        of F); a turn the frames do not vary along gets no slope."""
        turns = cls._turns(rotations, reference)
        mean_turn = turns.mean(axis=0)
        mean = readings.mean(axis=0)
        slope = np.linalg.lstsq(turns - mean_turn, readings - mean, rcond=None)[0]
        return cls(mean, slope, mean_turn, turns.min(axis=0), turns.max(axis=0), reference)

    @staticmethod
    def _turns(rotations, reference):
        return np.atleast_2d((rotations * reference.inv()).as_rotvec())[:, :2]

    def at(self, rotation):
        """(FEATURES,) the neutral's reading with the head posed `rotation`."""
        turn = np.clip(self._turns(rotation, self.reference)[0], self.least_turn, self.most_turn)
        return self.mean + (turn - self.mean_turn) @ self.slope


def turn_between(neutral, rotation):
    """The angle (deg) between the face's front in two head poses (model -> camera), the
    actor's calibrated `neutral` and `rotation`; a roll about the front does not count."""
    front = np.array([0.0, 0.0, 1.0])
    cosine = rotation.apply(front) @ neutral.apply(front)
    return float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))


def points_solver(names, motion):
    """What the map reads beside the face's image: its keys' weights (K,) from the points'
    displacement from the neutral (n, 3), the bounded solve (WeightSolver.solve) against the
    keys' motion at the tracker's points (K, n, 3)."""
    return WeightSolver(motion, names)


# The map's share in the motion that an avatar's keys of other names follow (AppearanceMap.
# motion_of, beside the points' own motion): the learnt `share` is chosen for the keys it reads
# by name. Measured on the rendered ICT takes tracked onto their own heads with every key renamed
# (so that all follow the motion; the mean correlation over the bundled head moving and still
# and identity 7 moving) at 0.5 / 0.625 / 0.75 / 0.875 / 1: 0.892 / 0.909 / 0.920 / 0.924 /
# 0.918. On a face the map was not learnt from (the MakeHuman child wearing its own keys,
# blender_tests/blender/test_own_keys_take.py; moving, still) 0.804, 0.953 / 0.821, 0.953 /
# 0.833, 0.949 / 0.820, 0.935 / 0.741, 0.888.
MOTION_SHARE = 0.875


@dataclass(frozen=True)
class AppearanceMap:
    """What the map reads = clip([reading - neutral reading, the points' weights] @
    coefficients + intercept, 0, 1), the points' weights by points_solver from the same keys'
    motion; the keys' weights are that reading un-mixed by the map's response (unmixed); the
    expression the keys make is their located motion at the tracker's points."""
    names: tuple              # the library keys it reads
    coefficients: np.ndarray  # (FEATURES + K, K): the reading's rows, then the points weights'
    intercept: np.ndarray     # (K,)
    motion: np.ndarray        # (K, n, 3) each key's motion at the tracker's points (model axes)
    # the appearance's share in the expression the avatar's keys follow, the points' the rest
    share: float = 0.5
    # (K, 3) the tracked turn's error (a rotation vector in the head's axes) per unit of each
    # key's weight (learn_turn_bias; None: none taken off)
    turn_bias: np.ndarray = None
    # (K + 1, K) what the map reads per unit of each key's weight, then with no key (the last
    # row; learn_response); None: the map's reading is the weights
    response: np.ndarray = None
    # the penalty on the weights' squares when the reading is un-mixed (unmixed_weights): at
    # each turn from the calibrated pose of unmixing_turns (deg, rising; turn_between),
    # unmixing_ridges, and linear between them
    unmixing_turns: tuple = (0.0,)
    unmixing_ridges: tuple = (0.0,)

    @cached_property
    def _points_solver(self):
        return points_solver(self.names, self.motion)

    def weights(self, change, displacement, turn):
        """(K,) the keys' weights for a reading's change from the actor's neutral (FEATURES,)
        and the points' displacement from it (n, 3) in the same frame, the head turned `turn`
        deg from its calibrated pose (turn_between)."""
        return self.weights_read(change, self._points_solver.solve(displacement), turn)

    def weights_read(self, change, points_weights, turn):
        """weights() from the points' weights (K,) as points_solver gives them."""
        return self.unmixed(self.reading(change, points_weights), turn)

    def reading(self, change, points_weights):
        """(K,) what the map reads (before un-mixing) of a reading's change and the points'
        weights."""
        features = np.concatenate((change, points_weights))
        return np.clip(features @ self.coefficients + self.intercept, 0.0, 1.0)

    def unmixing_ridge(self, turn):
        """The un-mixing's penalty with the head turned `turn` deg from its calibrated pose."""
        return float(np.interp(turn, self.unmixing_turns, self.unmixing_ridges))

    def unmixed(self, read, turn):
        """(K,) the weights in [0, 1] whose response best explains what the map read (K,),
        less the penalty at the head's `turn` (deg) times their squares; `read` itself without
        a response."""
        if self.response is None:
            return read
        return unmixed_weights(read, self.response, self.unmixing_ridge(turn))

    def unbiased_turn(self, rotation, weights):
        """The head's turn (model -> camera) tracked as `rotation` while the keys' weights (K,)
        are read, less the error they make in it."""
        if self.turn_bias is None:
            return rotation
        return rotation * Rotation.from_rotvec(weights @ self.turn_bias).inv()

    def motion_of(self, weights):
        """(n, 3) the tracker's points' motion from the neutral that its keys' weights (K,)
        make."""
        return np.tensordot(weights, self.motion, axes=1)

    def keys_by_name(self, names):
        """[(j, the map's columns)] for each key j of `names` that the map reads by its name,
        or by both halves' for an ARKit key the library splits (their mean is its weight)."""
        columns = {name: c for c, name in enumerate(self.names)}
        found = []
        for j, name in enumerate(names):
            halves = ARKIT_SPLIT.get(name, (name,))
            if all(half in columns for half in halves):
                found.append((j, [columns[half] for half in halves]))
        return found


def learn_appearance_map(changes, points_weights, weights, names, motion, components, ridge):
    """The map from readings' changes (F, FEATURES) and the points' weights in the same frames
    (F, K; points_solver's) to known weights (F, K) of keys `names` moving the tracker's points
    by `motion` (K, n, 3): a ridge regression on both's leading principal `components`, the
    penalty `ridge` times their mean variance."""
    return learn_appearance_maps(changes, points_weights, weights, names, motion,
                                 [(components, ridge)])[0]


def learn_appearance_maps(changes, points_weights, weights, names, motion, choices):
    """learn_appearance_map for each (components, ridge) of `choices`, the principal axes
    found once. The edges and the points' weights are scaled to the shading's spread first, so
    that the principal axes weigh the three alike."""
    features = np.hstack((changes, points_weights))
    shading_spread = changes[:, :SHADING_FEATURES].std()
    scales = np.ones(features.shape[1])
    for block in (slice(SHADING_FEATURES, FEATURES), slice(FEATURES, None)):
        scales[block] = shading_spread / max(float(features[:, block].std()), 1e-12)
    features *= scales      # in place: the training frames' features are the build's largest array
    centre = features.mean(axis=0)
    _, singular, axes = np.linalg.svd(features - centre, full_matrices=False)
    targets = weights - weights.mean(axis=0)
    maps = []
    for components, ridge in choices:
        projection = axes[:components].T
        scores = (features - centre) @ projection
        penalty = ridge * np.mean(singular[:components] ** 2)
        solved = np.linalg.solve(scores.T @ scores + penalty * np.eye(components),
                                 scores.T @ targets)
        coefficients = projection @ solved
        intercept = weights.mean(axis=0) - centre @ coefficients
        coefficients *= scales[:, None]        # read from the features unscaled
        maps.append(AppearanceMap(tuple(names), coefficients, intercept, np.asarray(motion)))
    return maps


def learn_turn_bias(weights, errors, ridge):
    """(K, 3) the turn's error linear in the keys' weights, by ridge regression (penalty
    `ridge` times the frames' count) over takes: per take, the keys' weights read (F, K) and
    the turn's errors in the same frames (rotation vectors in the head's axes (F, 3)). Each
    take's are taken as they vary about its means: a take's constant error is its
    calibration's, not an expression's."""
    weights = np.vstack([w - w.mean(axis=0) for w in weights])
    errors = np.vstack([e - e.mean(axis=0) for e in errors])
    penalty = ridge * len(weights) * np.eye(weights.shape[1])
    return np.linalg.solve(weights.T @ weights + penalty, weights.T @ errors)


def unmixed_weights(read, response, ridge):
    """(K,) the weights w in [0, 1] minimising ||w @ response[:K] + response[K] - read||^2 +
    ridge ||w||^2: what a map read (K,) un-mixed by its response (K + 1, K; learn_response)."""
    keys = response.shape[1]
    return bounded_weights(np.vstack((response[:keys].T, np.sqrt(ridge) * np.eye(keys))),
                           np.concatenate((read - response[keys], np.zeros(keys))))


def learn_response(reads, weights, ridge=RESPONSE_RIDGE):
    """(K + 1, K) what a map reads (AppearanceMap.reading) per unit of each key's true weight,
    then with no key (the last row): least squares over frames of takes the map was not learnt
    from (reads, weights: lists by take of (T, K)), with a penalty `ridge` times the frames'
    count on the keys' rows."""
    truth = np.vstack(weights)
    design = np.column_stack((truth, np.ones(len(truth))))
    penalty = ridge * len(truth) * np.eye(design.shape[1])
    penalty[-1, -1] = 0.0
    return np.linalg.solve(design.T @ design + penalty, design.T @ np.vstack(reads))


def write_appearance_map(learned, path=data.APPEARANCE_MAP_FILE):
    np.savez_compressed(path, format_version=np.int64(MAP_VERSION),
                        names=np.array(learned.names),
                        coefficients=learned.coefficients.astype(np.float32),
                        intercept=learned.intercept.astype(np.float32),
                        motion=learned.motion.astype(np.float32), share=np.float64(learned.share),
                        turn_bias=(np.zeros((len(learned.names), 3)) if learned.turn_bias is None
                                   else learned.turn_bias).astype(np.float32),
                        response=(_no_response(len(learned.names)) if learned.response is None
                                  else learned.response).astype(np.float32),
                        unmixing_turns=np.asarray(learned.unmixing_turns, np.float64),
                        unmixing_ridges=np.asarray(learned.unmixing_ridges, np.float64))


def _no_response(keys):
    """The response of a map that reads each key's weight as it is: un-mixing changes nothing."""
    return np.vstack((np.eye(keys), np.zeros((1, keys))))


def read_appearance_map(path=data.APPEARANCE_MAP_FILE):
    stored = data.versioned_arrays(path, MAP_VERSION, "appearance map", REMEDY)
    return AppearanceMap(tuple(str(name) for name in stored["names"]),
                         stored["coefficients"].astype(np.float64),
                         stored["intercept"].astype(np.float64),
                         stored["motion"].astype(np.float64), float(stored["share"]),
                         stored["turn_bias"].astype(np.float64),
                         stored["response"].astype(np.float64),
                         tuple(float(t) for t in stored["unmixing_turns"]),
                         tuple(float(r) for r in stored["unmixing_ridges"]))


@lru_cache(maxsize=1)
def load_appearance_map():
    """The bundled appearance map (data/appearance_map.npz), read once per process."""
    return read_appearance_map()
