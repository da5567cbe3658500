"""The tracker model learnt from a detector's points (core.tracker_model.learn_tracker_model) and
the slide it adds to the fit (core.tracking.ShapeModel.pose_offset), on known answers: points
made by a known offset, under-responding expressions and a known slide with the head's turn, and
poses fitted from points that slide.
"""
import functools
from dataclasses import replace

import numpy as np
from scipy.spatial.transform import Rotation

from exclone_addon.core import data, eyes
from exclone_addon.core.library import load_library
from exclone_addon.core.registration import similarity_transform
from exclone_addon.core.tracker_model import (TrainingFrames, TrackerModel, learn_eye_slide,
                                              learn_pose_bias, learn_tracker_model,
                                              read_tracker_locations)
from exclone_addon.core.tracking import (FRONTAL, POSE_FEATURES, Camera, ShapeFitter, ShapeModel,
                                         calibrate_neutral)

CAMERA = Camera.from_image_size(640, 480)


@functools.lru_cache(maxsize=1)
def known_detector(noise_px=0.3):
    """Three heads (the bundled neutral, widened or narrowed by up to 4%) seen by a made-up
    detector whose points sit off the located ones by a shared offset and slide with the turn by
    a known A (both in the face's plane, library axes), follow each expression 0.6 of the way,
    with 0.3 px noise; 80 frames each, turns up to 35 deg."""
    library = load_library()
    locations = read_tracker_locations()
    rng = np.random.default_rng(4)
    located = locations.sample(library.mesh.vertices)
    deltas = locations.sample(library.deltas)
    centre = located.mean(axis=0)
    offset = np.column_stack((rng.normal(0, 0.15, (len(located), 2)), np.zeros(len(located))))
    # in the face's plane: along the line of sight a slide hardly shows (the prior keeps it 0)
    slide = rng.normal(0, 0.3, (len(POSE_FEATURES), len(located), 3)) * [1.0, 1.0, 0.0]
    # the slide is a function of the direction to the camera in the model's (canonical face's)
    # axes, which the mean neutral's similarity onto the canonical face gives
    model_axes = similarity_transform(located, data.canonical_face().vertices)[0]
    heads = []
    for widen in (1.0, 1.04, 0.96):
        neutral = centre + (located - centre) * [widen, 1.0, 1.0]
        frames = 80
        weights = np.where(rng.uniform(size=(frames, len(deltas))) < 0.04,
                           rng.uniform(0.3, 1.0, (frames, len(deltas))), 0.0)
        rotations = Rotation.from_euler("yxz", rng.uniform(-1, 1, (frames, 3)) * [35, 25, 15],
                                        degrees=True) * FRONTAL
        translations = np.column_stack((rng.uniform(-3, 3, frames), rng.uniform(-3, 3, frames),
                                        rng.uniform(40, 60, frames))) - rotations.apply(centre)
        points = np.empty((frames, len(located), 3))
        for k in range(frames):
            to_camera = -rotations[k].inv().apply(translations[k]) - centre
            seen = (neutral + offset + 0.6 * np.tensordot(weights[k], deltas, axes=1)
                    + np.tensordot(ShapeModel.pose_features((to_camera @ model_axes.T)[None])[0],
                                   slide, axes=1))
            points[k, :, :2] = CAMERA.project(rotations[k].apply(seen) + translations[k])
            points[k, :, :2] += rng.normal(0, noise_px, (len(located), 2))
            points[k, :, 2] = 0.0
        heads.append(TrainingFrames(points, weights, rotations, translations, neutral))
    learned = learn_tracker_model(locations, heads, library, CAMERA)
    return learned, offset, slide, heads, model_axes


def test_learning_recovers_a_known_slide_and_offset():
    learned, offset, slide, heads, model_axes = known_detector()
    # back into the library's axes: the learnt arrays are in the canonical face's
    mean_neutral = np.mean([h.neutral for h in heads], axis=0)
    centred = learned["mean"] - learned["mean"].mean(axis=0)
    truth = mean_neutral + offset
    truth_centred = truth - truth.mean(axis=0)
    scale = np.linalg.norm(centred) / np.linalg.norm(truth_centred)
    rotation, _ = Rotation.align_vectors(truth_centred, centred)
    mean_error = np.linalg.norm(rotation.apply(centred) / scale - truth_centred, axis=1)
    learned_slide = rotation.apply(learned["pose_offsets"].reshape(-1, 3)).reshape(slide.shape) / scale
    # the slide as a function of the turn (its coefficients' features are correlated) as the
    # camera sees it (across its line of sight), for directions to the camera up to 30 deg off
    # the face's axis
    angles = np.radians(np.stack(np.meshgrid(np.linspace(-30, 30, 7), np.linspace(-20, 20, 5)),
                                 axis=-1).reshape(-1, 2))
    directions = np.column_stack((np.sin(angles[:, 0]), np.sin(angles[:, 1]), np.cos(angles[:, 0])))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    features = ShapeModel.pose_features(directions)

    def seen(offsets):             # (D, n, 3) less their part along each line of sight
        offsets = np.tensordot(features, offsets, axes=1)
        sight = directions @ model_axes                  # the directions in the library's axes
        return offsets - np.einsum("dni,di->dn", offsets, sight)[..., None] * sight[:, None]

    true_slide = seen(slide)
    slide_error = np.linalg.norm(seen(learned_slide) - true_slide, axis=2)
    size = np.linalg.norm(true_slide, axis=2)
    print(f"\nknown detector: mean within {np.median(mean_error):.3f} cm median "
          f"({mean_error.max():.3f} max) of the truth; slide {np.median(size):.3f} cm median, "
          f"its error {np.median(slide_error):.4f} cm median ({slide_error.max():.3f} max)")
    assert np.median(mean_error) < 0.02 and np.median(slide_error) < 0.1 * np.median(size)


def test_slide_derivative_matches_finite_differences():
    rng = np.random.default_rng(2)
    model = ShapeModel(np.zeros((5, 3)), np.zeros((0, 5, 3)), np.zeros(0),
                       pose_offsets=rng.normal(size=(len(POSE_FEATURES), 5, 3)),
                       pose_centre=np.array([0.1, 0.2, 0.3]))
    rotation, translation = Rotation.from_rotvec([0.2, 3.0, 0.1]), np.array([1.0, -2.0, 50.0])
    slide, jacobian = model.pose_offset(rotation, translation, jacobian=True)
    step = 1e-6
    for k in range(6):
        d = np.zeros(6)
        d[k] = step
        moved = model.pose_offset(Rotation.from_rotvec(d[:3]) * rotation, translation + d[3:])
        np.testing.assert_allclose((moved - slide) / step, jacobian[:, :, k], atol=1e-4)


def test_fit_reads_the_pose_of_points_that_slide():
    """Points made by the learnt model itself at known turns up to 30 deg: with its slide the fit
    reads the turns within 0.05 deg; the same model without the slide misreads them."""
    learned = known_detector()[0]
    model = TrackerModel.from_learned(learned).shape_model
    rotations = Rotation.from_euler("yxz", [[30, 0, 0], [-20, 15, 5], [10, -20, -10]],
                                    degrees=True) * FRONTAL
    translation = np.array([0.0, 0.0, 50.0])
    errors = {}
    for name, fitted in (("with", model), ("without", replace(model, pose_offsets=None))):
        fitter = ShapeFitter(fitted, CAMERA, depth_weight=0.0)
        errors[name] = []
        for rotation in rotations:
            points = CAMERA.project(rotation.apply(model.mean + model.pose_offset(rotation, translation))
                                    + translation)
            fit = fitter.fit(points)
            errors[name].append(np.degrees((fit.rotation * rotation.inv()).magnitude()))
    print(f"\nturn error with the slide {max(errors['with']):.3f} deg, without "
          f"{max(errors['without']):.2f} deg")
    assert max(errors["with"]) < 0.05 and max(errors["without"]) > 0.5


def test_learning_recovers_how_far_the_detector_follows_expressions():
    """The made-up detector follows each expression 0.6 of the way: the learnt seen motion of the
    keys it saw in enough frames is that share of the located motion."""
    learned, _, _, heads, _ = known_detector()
    seen_in = np.sum([np.count_nonzero(h.weights, axis=0) for h in heads], axis=0)
    located = learned["deltas"].reshape(len(seen_in), -1)
    moving = (seen_in >= 6) & (np.linalg.norm(located, axis=1) > 0.5)
    seen = learned["seen_deltas"].reshape(len(seen_in), -1)[moving]
    share = np.einsum("ei,ei->e", seen, located[moving]) / np.einsum("ei,ei->e", located[moving],
                                                                     located[moving])
    print(f"\n{np.count_nonzero(moving)} keys: share {np.median(share):.3f} median "
          f"({share.min():.3f}-{share.max():.3f})")
    assert abs(np.median(share) - 0.6) < 0.05


def test_seen_modes_are_the_modes_combinations_of_the_seen_motion():
    rng = np.random.default_rng(3)
    mean, displacements = rng.normal(size=(20, 3)), rng.normal(size=(6, 20, 3))
    seen = rng.normal(size=(6, 20, 3))
    model = ShapeModel.from_displacements(mean, displacements, seen=seen)
    # the same combination of the examples gives each mode and its seen motion
    flat, seen_flat = displacements.reshape(6, -1), seen.reshape(6, -1)
    combination = np.linalg.lstsq(flat.T, model.modes.reshape(len(model.modes), -1).T, rcond=None)[0]
    np.testing.assert_allclose(model.seen_modes.reshape(len(model.modes), -1),
                               combination.T @ seen_flat, atol=1e-9)
    same = ShapeModel.from_displacements(mean, displacements, seen=displacements)
    np.testing.assert_allclose(same.seen_modes, same.modes, atol=1e-12)
    assert ShapeModel.from_displacements(mean, displacements).seen_modes is None


def test_learning_recovers_a_known_eye_slide():
    """The known detector's heads and turns, their eyes read as the geometry of each head's
    neutral sees lids and irises looking ahead that slide with the turn by a known amount (with
    0.005 eye widths of noise): learn_eye_slide finds the slide."""
    _, _, _, heads, model_axes = known_detector()
    rng = np.random.default_rng(8)
    slide = rng.normal(0, 0.03, (len(POSE_FEATURES), 2, eyes.READING_MEASURES))
    centre = np.mean([h.neutral for h in heads], axis=0).mean(axis=0)
    r = eyes.EYE_RADIUS_WIDTHS
    seen_heads = []
    for head in heads:
        geometry = eyes.EyeGeometry(head.neutral, CAMERA)
        measures = np.empty((len(head.weights), 2, eyes.READING_MEASURES))
        for k in range(len(measures)):
            to_camera = -head.rotations[k].inv().apply(head.translations[k]) - centre
            true = np.array([[0.15, -0.12, 0.0, 0.0]] * 2) + np.tensordot(
                ShapeModel.pose_features((to_camera @ model_axes.T)[None])[0], slide, axes=1)
            depth = eyes.IRIS_DEPTH_WIDTHS - r + r * np.sqrt(1.0 - (true[:, 2:] ** 2).sum(axis=1) / r ** 2)
            measures[k] = [geometry._reading_of(e, geometry._points(
                true[e, 0], true[e, 1], [*true[e, 2:], depth[e]]), head.rotations[k],
                head.translations[k]) for e in range(2)]
        seen_heads.append(replace(head, eyes=measures + rng.normal(0, 0.005, measures.shape)))
    learned = learn_eye_slide(seen_heads, load_library().names, CAMERA)
    features = ShapeModel.pose_features(Rotation.from_euler(
        "yx", rng.uniform(-1, 1, (200, 2)) * [30, 20], degrees=True).apply([0.0, 0.0, 1.0]))
    error = np.tensordot(features, learned - slide, axes=1)
    size = np.tensordot(features, slide, axes=1)
    assert np.abs(error).max() < 0.2 * np.abs(size).max(), (np.abs(error).max(), np.abs(size).max())


def test_learnt_rotation_bias_takes_out_a_known_bias():
    """The made-up detector's heads, their truth told turned about the face's vertical axis by 0.1
    rad per unit of the direction to the camera's x (up to 3.3 deg: a detector that misreads the
    turn by a rule the model does not hold, as FaceMesh does with a sneer): the bias learnt from
    those frames takes it out of the fits' rotations (learnt with a small ridge penalty: the
    shipped one, chosen on FaceMesh's frames, shrinks the bias by about a quarter). Measured: 1.85
    deg median -> 0.38 (the fits of the heads' own truth: 0.24 -> 0.16)."""
    learned, _, _, heads, model_axes = known_detector()
    tracker = TrackerModel.from_learned(learned)
    centre = np.mean([h.neutral for h in heads], axis=0).mean(axis=0)
    told = []
    for head in heads:
        to_camera = -head.rotations.inv().apply(head.translations) - centre
        x = (to_camera @ model_axes.T)[:, 0] / np.linalg.norm(to_camera, axis=1)
        turn = Rotation.from_rotvec(0.1 * x[:, None] * model_axes[1])     # the model's up axis
        told.append(replace(head, rotations=head.rotations * turn.inv()))
    tracker = replace(tracker, pose_bias=learn_pose_bias(tracker, told, CAMERA, ridge=1e-3))
    fitter = ShapeFitter(tracker.shape_model, CAMERA, depth_weight=0.0)
    errors = {"fitted": [], "unbiased": []}
    for head in told:
        # each head calibrated on its neutral frames, as a session and learn_pose_bias do
        neutral = ~np.any(head.weights, axis=1)
        _, actor, calibration = calibrate_neutral(fitter, head.points[neutral])
        fits = [actor.fit(points) for points in head.points]
        for name, read in (("fitted", lambda fit: fit.rotation), ("unbiased", tracker.unbiased_rotation)):
            # the model's axes in the library's: the best alignment of the neutral frames
            to_library = (head.rotations[neutral].inv()
                          * Rotation.concatenate([read(fit) for fit in calibration])).mean()
            errors[name] += [np.degrees(((truth * to_library).inv() * read(fit)).magnitude())
                             for fit, truth in zip(fits, head.rotations)]
    fitted, unbiased = (np.median(errors[name]) for name in ("fitted", "unbiased"))
    print(f"\nrotation error against the told truth: fitted {fitted:.2f} deg median, unbiased "
          f"{unbiased:.2f} ({max(errors['unbiased']):.2f} max)")
    assert fitted > 1.0 and unbiased < 0.5
