"""The face's appearance read for expressions (core.appearance) on known answers: a face image
made by a known affine map comes back onto the frontal grid exactly, a brighter light reads the
same, a map learnt from readings that are linear in known weights gives those weights back, a
turn bias learnt from errors linear in known weights takes those errors off, a map's response
learnt from reads that mix known weights un-mixes them (with a penalty that follows the head's
turn from its calibrated pose), and the shipped map's file is checked as the tracker model's is.
"""
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from exclone_addon.core import data
from exclone_addon.core.appearance import (FEATURES, FRONTAL_SIZE, GRADIENT_BINS,
                                           SHADING_FEATURES, FaceFrontaliser, NeutralReading,
                                           learn_appearance_map, learn_response,
                                           learn_turn_bias, read_appearance_map,
                                           turn_between, unmixed_weights,
                                           write_appearance_map)
from exclone_addon.core.errors import ExCloneError
from exclone_addon.core.library import load_library
from exclone_addon.core.tracker_model import load_tracker_model
from exclone_addon.core.tracking import FRONTAL


# The ramp's value at grid point (x, y): RAMP_LEVEL + RAMP_SLOPE @ (x, y).
RAMP_LEVEL = 40.0
RAMP_SLOPE = np.array([1.5, 0.8])


def _ramp_image(affine, size=(640, 480)):
    """A grey image whose value at pixel p is the ramp at affine^-1 p."""
    columns, rows = np.meshgrid(np.arange(size[0]), np.arange(size[1]))
    pixels = np.stack((columns, rows), axis=-1).astype(np.float64)
    grid = (pixels - affine[:, 2]) @ np.linalg.inv(affine[:, :2]).T
    return (RAMP_LEVEL + grid @ RAMP_SLOPE).astype(np.float32)


def _ramp_on_the_grid(frontaliser):
    """(the ramp's value at each grid pixel, which grid pixels lie on the face), (height, width)."""
    rows, columns = np.mgrid[0:FRONTAL_SIZE[1], 0:FRONTAL_SIZE[0]]
    expected = RAMP_LEVEL + RAMP_SLOPE[0] * columns + RAMP_SLOPE[1] * rows
    return expected, frontaliser.inside.reshape(FRONTAL_SIZE[1], FRONTAL_SIZE[0])


def test_a_face_made_by_an_affine_map_comes_back_onto_the_grid():
    mean = load_tracker_model().shape_model.mean
    frontaliser = FaceFrontaliser(mean)
    affine = np.array([[2.1, 0.3, 180.0], [-0.25, 2.0, 120.0]])   # turned, scaled, moved
    image_points = frontaliser.grid_points @ affine[:, :2].T + affine[:, 2]
    frontal = frontaliser.frontal(_ramp_image(affine), image_points)
    expected, inside = _ramp_on_the_grid(frontaliser)
    assert inside.mean() > 0.6
    assert np.abs(frontal - expected)[inside].max() < 0.05


def test_a_brighter_face_reads_the_same_and_off_the_face_its_shading_reads_nought():
    """The ramp's shading reads its brightness over the median; its edges, one direction
    everywhere (the ramp's gradient, 28 degrees from the grid's x axis), fall most in that
    direction's histogram bin."""
    mean = load_tracker_model().shape_model.mean
    frontaliser = FaceFrontaliser(mean)
    affine = np.array([[2.0, 0.0, 200.0], [0.0, 2.0, 140.0]])
    image_points = frontaliser.grid_points @ affine[:, :2].T + affine[:, 2]
    image = _ramp_image(affine)
    reading = frontaliser.reading(image, image_points)
    brighter = frontaliser.reading(1.6 * image, image_points)
    assert reading.shape == (FEATURES,)
    np.testing.assert_allclose(brighter, reading, atol=1e-5)
    shading = reading[:SHADING_FEATURES]
    on_face = shading != 0
    assert 0.5 < on_face.mean() < 1.0     # the grid's corners are off the face
    assert np.median(shading[on_face]) == pytest.approx(1.0, abs=0.02)
    # the bins split 0-180 degrees
    bins = reading[SHADING_FEATURES:].reshape(-1, GRADIENT_BINS).sum(axis=0)
    direction = np.degrees(np.arctan2(RAMP_SLOPE[1], RAMP_SLOPE[0]))
    assert bins.argmax() == int(direction // (180 / GRADIENT_BINS))


def test_a_map_learnt_from_linear_readings_gives_the_weights_back():
    """The readings linear in the weights; the points' weights a faint, noisy echo of them (as
    FaceMesh's points read a frown): the map reads the weights back from both, the points'
    weights solved from their displacement as the session solves them."""
    rng = np.random.default_rng(4)
    keys, frames = 5, 600
    effects = rng.normal(size=(keys, FEATURES))
    weights = rng.uniform(0, 1, (frames, keys)) * (rng.uniform(size=(frames, keys)) < 0.4)
    changes = weights @ effects + 0.01 * rng.normal(size=(frames, FEATURES))
    points = np.clip(0.3 * weights + 0.05 * rng.normal(size=(frames, keys)), 0.0, 1.0)
    motion = rng.normal(size=(keys, 468, 3))
    learned = learn_appearance_map(changes, points, weights, [f"key{j}" for j in range(keys)],
                                   motion, components=40, ridge=1e-6)
    held_out = rng.uniform(0, 1, (50, keys))
    read = np.array([learned.weights(change, np.tensordot(0.3 * w, motion, axes=1), 0.0)
                     for change, w in zip(held_out @ effects, held_out)])
    np.testing.assert_allclose(read, held_out, atol=0.01)
    np.testing.assert_allclose(learned.motion_of(read[0]),
                               np.tensordot(held_out[0], motion, axes=1), atol=0.05)
    assert learned.weights_read(-3 * effects.sum(axis=0), np.zeros(keys), 0.0).max() == 0.0


def test_a_turn_bias_learnt_from_errors_linear_in_the_weights_takes_them_off():
    """Each take's turn error: its own constant (its calibration's) plus a known linear effect
    of the keys' weights and a little noise; the bias learnt over the takes takes the effect off
    a turn tracked with the error on the head's side (model axes)."""
    rng = np.random.default_rng(6)
    keys = 4
    effect = np.radians(rng.uniform(-3, 3, (keys, 3)))
    weights, errors = [], []
    for _ in range(6):
        w = rng.uniform(0, 1, (200, keys)) * (rng.uniform(size=(200, keys)) < 0.5)
        weights.append(w)
        errors.append(w @ effect + np.radians(rng.uniform(-2, 2, 3))
                      + np.radians(0.05) * rng.normal(size=(200, 3)))
    bias = learn_turn_bias(weights, errors, ridge=1e-6)
    np.testing.assert_allclose(bias, effect, atol=np.radians(0.02))
    learned = replace(learn_appearance_map(np.eye(keys, FEATURES), np.eye(keys), np.eye(keys), [
        f"key{j}" for j in range(keys)], np.zeros((keys, 468, 3)), components=2, ridge=1.0),
        turn_bias=bias)
    true = Rotation.from_euler("yxz", [20, -10, 5], degrees=True)
    read = np.array([0.8, 0.0, 0.5, 1.0])
    tracked = true * Rotation.from_rotvec(read @ effect)
    assert np.degrees((learned.unbiased_turn(tracked, read) * true.inv()).magnitude()) < 0.05
    assert np.degrees((tracked * true.inv()).magnitude()) > 1.0
    assert replace(learned, turn_bias=None).unbiased_turn(tracked, read) is tracked


def test_a_response_learnt_from_mixed_reads_unmixes_them():
    """A map's reads: each key at a fraction of its weight, some of the others' leaking in, an
    offset and a little noise (as a ridge map reads on frames it was not learnt from). The
    response is learnt back, and un-mixing a read of sparse weights gives them back (the bounds
    keep the keys that are not there at nought); a small penalty shrinks them a little."""
    rng = np.random.default_rng(8)
    keys = 6
    mixing = np.diag(rng.uniform(0.15, 0.6, keys)) + 0.1 * rng.uniform(-1, 1, (keys, keys))
    offset = rng.uniform(0.0, 0.05, keys)
    truths = [rng.uniform(0, 1, (300, keys)) * (rng.uniform(size=(300, keys)) < 0.3)
              for _ in range(4)]
    reads = [t @ mixing + offset + 0.002 * rng.normal(size=t.shape) for t in truths]
    response = learn_response(reads, truths)
    np.testing.assert_allclose(response, np.vstack((mixing, offset)), atol=0.003)
    true = np.array([0.0, 0.9, 0.0, 0.0, 0.4, 0.0])
    read = true @ mixing + offset
    np.testing.assert_allclose(unmixed_weights(read, response, 0.0), true, atol=0.02)
    assert np.abs(read - true).max() > 0.2         # un-mixing is not nothing
    shrunk = unmixed_weights(read, response, 0.01)
    assert np.abs(shrunk - true).max() < 0.1 and shrunk.sum() < true.sum()
    # weights are kept within [0, 1]
    assert unmixed_weights(3 * read, response, 0.0).max() <= 1.0


def test_the_unmixing_penalty_follows_the_head_turn_from_its_calibrated_pose_not_its_roll():
    """The turn is the angle between the face's front in the calibrated pose and now, whatever
    the head's roll about the front; the un-mixing's penalty is the map's at each knot's turn,
    linear between them and held beyond them, and a larger one shrinks the same read's
    weights."""
    neutral = Rotation.from_euler("yx", [5, -12], degrees=True) * FRONTAL
    assert turn_between(neutral, neutral) == pytest.approx(0.0, abs=1e-6)
    for axes, angles, turn in (("y", 30, 30), ("x", -20, 20), ("z", 45, 0), ("zy", (40, 25), 25)):
        # turned about the head's own axes: z is its front
        turned = neutral * Rotation.from_euler(axes, angles, degrees=True)
        assert turn_between(neutral, turned) == pytest.approx(turn, abs=1e-6)
    rng = np.random.default_rng(3)
    learned = replace(learn_appearance_map(np.eye(2, FEATURES), np.eye(2), np.eye(2), [
        "jawOpen", "mouthPucker"], np.zeros((2, 468, 3)), components=2, ridge=1.0),
        response=np.vstack((np.diag([0.3, 0.2]), [0.01, 0.02])) + 0.02 * rng.uniform(size=(3, 2)),
        unmixing_turns=(10.0, 30.0), unmixing_ridges=(0.1, 0.5))
    assert [learned.unmixing_ridge(t) for t in (0.0, 10.0, 20.0, 30.0, 50.0)] == pytest.approx(
        [0.1, 0.1, 0.3, 0.5, 0.5])
    read = np.array([0.2, 0.12])
    facing, turned = learned.unmixed(read, 0.0), learned.unmixed(read, 40.0)
    np.testing.assert_allclose(facing, unmixed_weights(read, learned.response, 0.1))
    assert np.all(turned < facing) and facing.min() > 0.1


def test_keys_are_read_by_name_or_by_their_halves():
    learned = learn_appearance_map(np.eye(4, FEATURES), np.eye(4, 3), np.eye(4, 3), [
        "jawOpen", "cheekPuff_L", "cheekPuff_R"], np.zeros((3, 468, 3)), components=2, ridge=1.0)
    names = ["cheekPuff", "jawOpen", "eyeBlink_L", "mouthSmile_L", "cheekPuff_R"]
    assert learned.keys_by_name(names) == [(0, [1, 2]), (1, [0]), (4, [2])]


def test_the_map_file_round_trips_and_a_missing_or_old_one_says_what_to_run(tmp_path):
    rng = np.random.default_rng(1)
    changes, weights = rng.normal(size=(60, FEATURES)), rng.uniform(size=(60, 2))
    learned = replace(learn_appearance_map(changes, rng.uniform(size=(60, 2)), weights,
                                           ["jawOpen", "mouthPucker"], np.zeros((2, 468, 3)),
                                           components=10, ridge=0.1),
                      turn_bias=rng.normal(size=(2, 3)))
    path = tmp_path / "map.npz"
    # a map without a response writes one that changes nothing
    write_appearance_map(learned, path)
    change, points = rng.normal(size=FEATURES), rng.uniform(size=2)
    np.testing.assert_allclose(read_appearance_map(path).weights_read(change, points, 10.0),
                               learned.weights_read(change, points, 10.0), atol=1e-5)
    learned = replace(learned, response=rng.uniform(size=(3, 2)), unmixing_turns=(5.0, 25.0),
                      unmixing_ridges=(0.03, 0.3))
    write_appearance_map(learned, path)
    read = read_appearance_map(path)
    assert read.names == ("jawOpen", "mouthPucker")
    np.testing.assert_allclose(read.coefficients, learned.coefficients, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(read.turn_bias, learned.turn_bias, rtol=1e-6)
    np.testing.assert_allclose(read.response, learned.response, rtol=1e-6)
    assert read.unmixing_turns == (5.0, 25.0) and read.unmixing_ridges == (0.03, 0.3)
    with pytest.raises(ExCloneError, match="make_appearance_model"):
        read_appearance_map(tmp_path / "missing.npz")
    with np.load(path) as stored:
        arrays = dict(stored)
    arrays["format_version"] = np.int64(0)
    np.savez(path, **arrays)
    with pytest.raises(ExCloneError, match="old format"):
        read_appearance_map(path)


def test_the_shipped_map_reads_the_library_keys_the_eyes_do_not_as_the_tracker_moves_them():
    """Its keys' motion is the shipped tracker model's: a map learnt before the tracker model
    last changed fails here (run scripts/make_appearance_model.py)."""
    shipped = read_appearance_map(data.APPEARANCE_MAP_FILE)
    names = list(load_library().names)
    assert shipped.coefficients.shape == (FEATURES + len(shipped.names), len(shipped.names))
    assert "jawOpen" in shipped.names and not any(n.startswith("eye") for n in shipped.names)
    tracked = load_tracker_model().expressions[[names.index(n) for n in shipped.names]]
    np.testing.assert_allclose(shipped.motion, tracked, atol=1e-5)
    assert 0.0 <= shipped.share <= 1.0
    assert shipped.turn_bias.shape == (len(shipped.names), 3)
    assert shipped.response.shape == (len(shipped.names) + 1, len(shipped.names))
    # every key raises its own reading
    assert np.all(np.diag(shipped.response) > 0)
    assert np.all(np.diff(shipped.unmixing_turns) > 0) and min(shipped.unmixing_ridges) > 0.0


def _noisy_grid_error(affine, noise, rng):
    """The frontal grid's error (its standard deviation over the face) reading a ramp seen
    through `affine` with Gaussian noise of `noise` grey levels per image pixel."""
    frontaliser = FaceFrontaliser(load_tracker_model().shape_model.mean)
    image_points = frontaliser.grid_points @ affine[:, :2].T + affine[:, 2]
    image = _ramp_image(affine) + rng.normal(0.0, noise, (480, 640)).astype(np.float32)
    frontal = frontaliser.frontal(image, image_points)
    expected, inside = _ramp_on_the_grid(frontaliser)
    return float(np.std((frontal - expected)[inside]))


def test_the_grid_reads_a_noisy_image_smoothed_at_its_scale(monkeypatch):
    """A face 2.6 image pixels per grid pixel (a face about 200 pixels wide): each grid pixel
    averages its footprint's noise instead of taking one pixel's; a grid pixel larger than an
    image pixel (a small face) is not smoothed. Measured: 3.2 grey levels smoothed, 6.9 sampled
    (noise of 10)."""
    rng = np.random.default_rng(0)
    large = np.array([[2.6, 0.0, 150.0], [0.0, 2.6, 100.0]])
    smoothed = _noisy_grid_error(large, 10.0, rng)
    small = _noisy_grid_error(np.array([[0.8, 0.0, 250.0], [0.0, 0.8, 200.0]]), 10.0, rng)
    monkeypatch.setattr("exclone_addon.core.appearance.GRID_ANTIALIAS", 0.0)
    sampled = _noisy_grid_error(large, 10.0, rng)
    assert smoothed < 0.6 * sampled, (smoothed, sampled)
    assert small > 0.8 * sampled, (small, sampled)


def test_the_neutral_reading_follows_the_turn_within_the_calibrations_range():
    """Readings linear in the pitch and yaw come back from the fitted line inside the range the
    calibration turned through, and are held at its edge beyond; a roll moves nothing."""
    rng = np.random.default_rng(1)
    reference = Rotation.from_euler("y", 180, degrees=True)
    turns = np.column_stack((rng.uniform(-0.1, 0.1, 30), rng.uniform(-0.17, 0.17, 30)))
    mean, slope = rng.normal(size=FEATURES), rng.normal(size=(2, FEATURES))
    readings = mean + turns @ slope
    rotations = Rotation.from_rotvec(np.column_stack((turns, np.zeros(30)))) * reference
    neutral = NeutralReading.fitted(readings, rotations, reference)
    inside = Rotation.from_rotvec([0.05, -0.1, 0.0]) * reference
    np.testing.assert_allclose(neutral.at(inside), mean + [0.05, -0.1] @ slope, atol=1e-8)
    beyond = Rotation.from_rotvec([0.5, -0.1, 0.0]) * reference
    edge = Rotation.from_rotvec([turns[:, 0].max(), -0.1, 0.0]) * reference
    np.testing.assert_allclose(neutral.at(beyond), neutral.at(edge), atol=1e-8)
    rolled = Rotation.from_rotvec([0.0, 0.0, 0.3]) * reference
    np.testing.assert_allclose(neutral.at(rolled), neutral.at(reference), atol=1e-8)
    still = NeutralReading.fitted(readings[:1].repeat(5, axis=0),
                                  Rotation.concatenate([rotations[0]] * 5), reference)
    np.testing.assert_allclose(still.at(beyond), readings[0], atol=1e-8)
