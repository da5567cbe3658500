"""Write exclone_addon/data/appearance_map.npz, what the live session reads expressions from
besides the points (core.appearance, docs/method.md §12):

1. takes of ICT identities (none the tests' rendered takes use, none the tracker model learnt
   from), each a second of a neutral face turning a little (the session's calibration) and then
   random library expressions (1-2 keys at 0.3-1 rising and falling, neutral spells, the eyes
   blinking and looking about on their own) with the head turning up to 30 / 20 / 12 deg, under
   Workbench's studio lights, skin tinted; rendered in background Blender at 640x480 (about
   0.15 CPU s a frame, cached in --work);
2. each take tracked by core.session.FaceTrackingSession as a camera's frames are, and each
   frame's face read as the session reads it (core.appearance: the face frontalised by the
   tracked pose, less the take's calibrated neutral face), beside the keys' weights its points'
   expression gives;
3. a ridge map from those readings and points' weights to the library's keys the eyes do not
   read (and that move the face)
   (core.appearance.learn_appearance_map), its principal components and penalty chosen by
   leaving a quarter of the takes out at a time;
4. the appearance's share beside the points' in what the avatar's keys follow: a quarter of
   the takes tracked again onto their own heads with a map (and its response, step 5) learnt
   without them, at each share;
5. the map's response: what it reads per unit of each key's weight, on frames of takes it was
   not learnt from (the folds' maps), by which its reading is un-mixed, the un-mixing's penalty
   chosen per band of the head's tracked turn from its calibrated pose by the folds' squared
   error (responses learnt without the fold's takes);
6. the turn's bias: the tracked head turn's error against the take's true turn, linear in the
   weights the map gives (maps learnt without the take's fold), its penalty chosen by the folds.

Run it after make_tracker_model.py (the readings go through the tracker).

    .venv/bin/python scripts/make_appearance_model.py [--work DIR] [--jobs N]
"""
import sys
import time
from dataclasses import replace
from concurrent.futures import ProcessPoolExecutor
from itertools import repeat
from multiprocessing import get_context
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from exclone_addon.core import appearance  # noqa: E402
from exclone_addon.core.data import APPEARANCE_MAP_FILE  # noqa: E402
from exclone_addon.core.library import load_library  # noqa: E402
from exclone_addon.core.retarget import AvatarRig  # noqa: E402
from exclone_addon.core.session import FaceTrackingSession  # noqa: E402
from exclone_addon.core.tracker_model import (EYE_KEY_PREFIX, load_tracker_model,  # noqa: E402
                                              read_tracker_locations)
from exclone_addon.core.tracking import FRONTAL, Camera  # noqa: E402
from make_tracker_model import (identity_vertices, render_identity,  # noqa: E402
                                require_identities, training_parser)

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "scripts"))     # render_faces (in each rendering process too)
# ICT identity seeds: the tests' rendered takes use the bundled face and seed 7, the tracker
# model seeds 101-108.
TRAINING_IDENTITIES = tuple(range(301, 397))
# Of those, the ones whose take holds a neutral face (the eyes still blinking and looking about)
# while the head turns: a turning head changes the face's shading, which is no expression.
NEUTRAL_IDENTITIES = tuple(range(349, 357)) + tuple(range(389, 397))
TAKE_FRAMES = 360
CALIBRATION_FRAMES = 30       # the session's default calibration: one second at 30 fps
FPS = 30.0
IMAGE_SIZE = (640, 480)
TURN_DEG = (30.0, 20.0, 12.0)  # the largest turn about y, x, z (camera axes)
BUMP_FRAMES = 20              # an expression rises and falls over this many frames
BUMP_SPACING = 10             # one starts every this many frames (two overlap)
NEUTRAL_SHARE = 0.2           # of the bumps, left out (a neutral spell)
EYE_BUMP_FRAMES = 8           # a blink or a look: a quarter second
EYE_SHARE = 0.3               # of the bump slots, where an eye key rises too
RECIPE_VERSION = 1
# What the map is chosen from: its principal components and ridge penalty (a share of their
# mean variance), each pair scored by the mean correlation of its weights with the truth on
# takes left out (FOLDS of them).
COMPONENTS = (800, 1500, 2500)
RIDGES = (0.01, 0.1, 0.3)
FOLDS = 4
SHARES = (0.5, 0.625, 0.75, 0.875, 1.0)
# The un-mixing's penalties (AppearanceMap.unmixing_ridge) it is chosen from, by the folds'
# squared error: the correlation cannot see the un-mixing scale a misread up with an expression.
# One is chosen per band of the head's turn from its calibrated pose (deg; bands between these
# edges): on the folds' frames the best penalty grew with the turn (docs/method.md §12).
UNMIXING_RIDGES = (0.03, 0.05, 0.1, 0.2, 0.3, 0.5)
UNMIXING_TURN_EDGES = (10.0, 20.0, 30.0)
# The turn bias's ridge penalties (per frame) it is chosen from, by the folds' median turn error.
TURN_RIDGES = (1e-4, 1e-3, 1e-2)
MOVES_CM = 0.01     # a key the map reads moves some tracker point this far (the pupils' do not)


def _bump(frames):
    return 0.5 - 0.5 * np.cos(2 * np.pi * np.arange(frames) / (frames - 1))


def take_recipe(identity, names):
    """(weights (T, E), rotations model -> camera (T), translations of the head's centre (T, 3),
    skin tint, studio light) of one identity's take, from a generator seeded by the identity."""
    rng = np.random.default_rng(2000 + identity)
    eye_keys = [j for j, name in enumerate(names) if name.startswith(EYE_KEY_PREFIX)]
    other_keys = [j for j in range(len(names)) if j not in eye_keys]
    jaw, close = names.index("jawOpen"), names.index("mouthClose")
    weights = np.zeros((TAKE_FRAMES, len(names)))
    for start in range(CALIBRATION_FRAMES, TAKE_FRAMES - BUMP_FRAMES, BUMP_SPACING):
        if rng.uniform() >= (1.0 if identity in NEUTRAL_IDENTITIES else NEUTRAL_SHARE):
            keys = rng.choice(other_keys, rng.integers(1, 3), replace=False)
            amounts = rng.uniform(0.3, 1.0, len(keys))
            span = slice(start, start + BUMP_FRAMES)
            weights[span, keys] += amounts * _bump(BUMP_FRAMES)[:, None]
            if close in keys:       # the lips closed over an open jaw, as the library means it
                weights[span, jaw] += amounts[list(keys).index(close)] * _bump(BUMP_FRAMES)
        if rng.uniform() < EYE_SHARE:
            key = rng.choice(eye_keys)
            span = slice(start, start + EYE_BUMP_FRAMES)
            weights[span, key] += rng.uniform(0.5, 1.0) * _bump(EYE_BUMP_FRAMES)
    weights = np.clip(weights, 0.0, 1.0)
    t = np.arange(TAKE_FRAMES) / FPS
    since = t - CALIBRATION_FRAMES / FPS
    size = rng.uniform(0.5, 1.0, 3) * TURN_DEG
    frequency, phase = rng.uniform(0.1, 0.3, 3), rng.uniform(0, 2 * np.pi, 3)
    ease = np.clip(since, 0.0, 1.0)[:, None]        # from still over the first second
    angles = ease * size * np.sin(2 * np.pi * frequency * since[:, None] + phase)
    c = t[:CALIBRATION_FRAMES]
    angles[:CALIBRATION_FRAMES] = np.column_stack((10 * np.sin(2 * np.pi * c),
                                                   6 * np.sin(4 * np.pi * c), 0 * c))
    rotations = Rotation.from_euler("yxz", angles, degrees=True) * FRONTAL
    translations = np.tile([rng.uniform(-3, 3), rng.uniform(-2, 2), rng.uniform(42, 58)],
                           (TAKE_FRAMES, 1))
    import render_faces     # needs bpy (its studio lights' names)
    light = render_faces.STUDIO_LIGHTS[identity % len(render_faces.STUDIO_LIGHTS)]
    return weights, rotations, translations, rng.uniform(0.75, 1.15), light


def take_folder(work, identity):
    return work / f"v{RECIPE_VERSION}-identity{identity}"


def render_take(work, identity, identities_file):
    """Renders one identity's take into its folder under `work` (skipped when it is there);
    returns the frames' paths."""
    library = load_library()
    weights, rotations, translations, tint, light = take_recipe(identity, list(library.names))
    begun = time.time()
    paths = render_identity(take_folder(work, identity), library,
                            identity_vertices(library, identity, identities_file),
                            (weights, rotations, translations, tint), read_tracker_locations(),
                            studio_light=light)
    print(f"make_appearance_model: identity {identity}: {len(paths)} frames in "
          f"{time.time() - begun:.0f} s", flush=True)
    return paths


def read_take(paths, points_solver=None, avatar=None, appearance_map=True):
    """((T, appearance.FEATURES) each frame's reading as a tracking session makes it, (T, K)
    the points' expression's weights by `points_solver` (appearance.points_solver; K = 0
    without it), (T, E) the library keys' weights onto `avatar` read with `appearance_map` (the
    session's `appearance`: without an avatar no map is loaded), (T, 4) the tracked turn (model
    -> camera, quaternions), (T,) its angle from the calibrated pose (deg, appearance.
    turn_between)), NaN where the session had no face or was calibrating (and without an
    avatar)."""
    session = FaceTrackingSession(avatar=avatar, camera=Camera.from_image_size(*IMAGE_SIZE),
                                  calibration_frames=CALIBRATION_FRAMES, appearance=appearance_map)
    readings = np.full((len(paths), appearance.FEATURES), np.nan)
    points = np.full((len(paths), len(points_solver.names) if points_solver else 0), np.nan)
    weights = np.full((len(paths), len(avatar.names) if avatar else 0), np.nan)
    turns = np.full((len(paths), 4), np.nan)
    from_neutral = np.full(len(paths), np.nan)
    for k, path in enumerate(paths):
        result = session.step(cv2.imread(str(path)), k / FPS)
        if session.expression_reading is not None:
            readings[k] = session.expression_reading
            turns[k] = result.rotation.as_quat()
            from_neutral[k] = appearance.turn_between(session.neutral_rotation, result.rotation)
            if points_solver is not None:
                points[k] = points_solver.solve(session.expression_displacement)
        if result.weights is not None:
            weights[k] = [result.weights[name] for name in avatar.names]
    return readings, points, weights, turns, from_neutral


def _folds(count, fold):
    """(the takes learnt from, the takes left out) of `count` takes for one fold."""
    return ([k for k in range(count) if k % FOLDS != fold],
            [k for k in range(count) if k % FOLDS == fold])


def held_out_weights(readings, points, weights, choices):
    """Per (components, ridge) of `choices`, each take's weights (T, K) read by the map learnt
    without its fold (readings, points, weights: lists by take of (T, FEATURES), the points'
    weights (T, K), the true weights (T, K))."""
    found = {choice: [None] * len(readings) for choice in choices}
    for fold in range(FOLDS):
        learnt, left = _folds(len(readings), fold)
        maps = appearance.learn_appearance_maps(
            np.vstack([readings[k] for k in learnt]), np.vstack([points[k] for k in learnt]),
            np.vstack([weights[k] for k in learnt]), [], np.zeros((weights[0].shape[1], 0, 3)),
            choices)
        for choice, learned in zip(choices, maps):
            for k in left:
                found[choice][k] = np.array([learned.reading(change, read) for change, read
                                             in zip(readings[k], points[k])])
    return found


def _moving_correlations(estimate, truth):
    """Each key's correlation of its estimate with the truth (frames, keys), over the keys that
    move in the truth."""
    return [np.corrcoef(estimate[:, j], truth[:, j])[0, 1]
            for j in np.flatnonzero(truth.std(axis=0) > 0)]


def held_out_scores(read, weights):
    """Per choice, the mean correlation with the truth over the keys (those that move in each
    fold's takes) of held_out_weights' weights `read` (weights: the truth by take)."""
    scores = {}
    for choice, taken in read.items():
        values = []
        for fold in range(FOLDS):
            left = _folds(len(weights), fold)[1]
            values += _moving_correlations(np.vstack([taken[k] for k in left]),
                                           np.vstack([weights[k] for k in left]))
        scores[choice] = float(np.nanmean(values))
    return scores


def held_out_unmixing(read, weights, ridges_by_frame):
    """Each take's held-out reads `read` (held_out_weights') un-mixed by the response learnt
    from the other folds' takes (weights: the truth by take), per name of `ridges_by_frame`:
    {name: each take's penalty per frame (T,)}."""
    unmixed = {name: [None] * len(read) for name in ridges_by_frame}
    for fold in range(FOLDS):
        learnt, left = _folds(len(read), fold)
        response = appearance.learn_response([read[k] for k in learnt],
                                             [weights[k] for k in learnt])
        for name, ridges in ridges_by_frame.items():
            for k in left:
                unmixed[name][k] = np.array([appearance.unmixed_weights(frame, response, ridge)
                                             for frame, ridge in zip(read[k], ridges[k])])
    return unmixed


def held_out_squared_errors(read, weights, frames=slice(None)):
    """Per choice, the mean squared error against the truth (weights, by take) of held-out
    weights `read` (by choice, lists by take) over `frames` (an index into the takes' frames
    stacked; all of them by default)."""
    truth = np.vstack(weights)[frames]
    return {choice: float(np.mean((np.vstack(taken)[frames] - truth) ** 2))
            for choice, taken in read.items()}


def held_out_unmixing_by_turn(read, weights, turns):
    """The un-mixing's penalties by turn (AppearanceMap's unmixing_turns, unmixing_ridges): per
    band of the turn from the calibrated pose (UNMIXING_TURN_EDGES), the penalty of
    UNMIXING_RIDGES whose held-out un-mixed weights have the least squared error there, at the
    band's median turn; the held-out weights un-mixed by them; and each band's squared error by
    penalty (read, weights, turns: lists by take of held_out_weights' reads, the truth and the
    turns from the calibrated pose (T,), deg)."""
    unmixed = held_out_unmixing(read, weights, {ridge: [np.full(len(r), ridge) for r in read]
                                                for ridge in UNMIXING_RIDGES})
    angle = np.concatenate(turns)
    band = np.searchsorted(UNMIXING_TURN_EDGES, angle)
    errors, knots, ridges = {}, [], []
    for b in range(len(UNMIXING_TURN_EDGES) + 1):
        inside = band == b
        errors[b] = held_out_squared_errors(unmixed, weights, inside)
        knots.append(float(np.median(angle[inside])))
        ridges.append(min(errors[b], key=errors[b].get))
    by_turn = held_out_unmixing(read, weights, {
        "by turn": [np.interp(a, knots, ridges) for a in turns]})["by turn"]
    return (tuple(knots), tuple(ridges)), by_turn, unmixed, errors


def turn_errors(turns, true_turns):
    """(T, 3) the tracked turns' errors (quaternions (T, 4), model -> camera) against the true
    ones (Rotations), as rotation vectors in the head's axes, less their mean (the tracker's
    model frame differs from the head's by a constant turn)."""
    error = true_turns.inv() * Rotation.from_quat(turns)
    return (error * error.mean().inv()).as_rotvec()


def held_out_turn_ridge(read, errors):
    """The ridge (TURN_RIDGES) whose turn bias, learnt without each fold's takes, leaves their
    turn errors smallest (median angle), and each ridge's median in degrees (read, errors:
    lists by take of held-out weights (T, K) and turn errors (T, 3))."""
    scores = {}
    for ridge in TURN_RIDGES:
        left_errors = []
        for fold in range(FOLDS):
            learnt, left = _folds(len(read), fold)
            bias = appearance.learn_turn_bias([read[k] for k in learnt],
                                              [errors[k] for k in learnt], ridge)
            left_errors += [errors[k] - (read[k] - read[k].mean(axis=0)) @ bias for k in left]
        remaining = np.vstack([e - e.mean(axis=0) for e in left_errors])
        scores[ridge] = float(np.degrees(np.median(np.linalg.norm(remaining, axis=1))))
    return min(scores, key=scores.get), scores


def held_out_share(pool, paths, truths, changes, points, weights, keys, names, motion, choice,
                   read, identities_file):
    """The share (SHARES) whose weights correlate best with the truth, averaged over the keys
    the map reads that move, on the first fold's takes tracked onto their own heads (in `pool`'s
    processes), and each share's score (lists by take: frame paths, true weights (T, E), and the
    calibrated frames' readings, points' weights, the map's keys' weights and their held-out
    reads (held_out_weights'); keys: the map's; choice: the map's components, ridge and
    un-mixing's penalties by turn)."""
    components, ridge, (unmixing_turns, unmixing_ridges) = choice
    library = load_library()
    locations = read_tracker_locations()
    learnt, left = _folds(len(paths), 0)
    learned = appearance.learn_appearance_map(
        np.vstack([changes[k] for k in learnt]), np.vstack([points[k] for k in learnt]),
        np.vstack([weights[k] for k in learnt]), [names[j] for j in keys], motion[keys],
        components, ridge)
    learned = replace(learned, unmixing_turns=unmixing_turns, unmixing_ridges=unmixing_ridges,
                      response=appearance.learn_response([read[k] for k in learnt],
                                                         [weights[k] for k in learnt]))
    runs = [(k, share) for k in left for share in SHARES]
    avatars = {k: AvatarRig.from_locations(
        identity_vertices(library, TRAINING_IDENTITIES[k], identities_file), library.deltas,
        names, locations) for k in left}
    reads = pool.map(read_take, [paths[k] for k, _ in runs], repeat(None),
                     [avatars[k] for k, _ in runs],
                     [replace(learned, share=share) for _, share in runs])
    tracked = {share: [] for share in SHARES}
    for (_, share), taken in zip(runs, reads):
        tracked[share].append(taken[2])
    truth = np.vstack([truths[k] for k in left])[:, keys]
    scores = {}
    for share, taken in tracked.items():
        estimate = np.vstack(taken)[:, keys]
        seen = np.all(np.isfinite(estimate), axis=1)
        scores[share] = float(np.nanmean(_moving_correlations(estimate[seen], truth[seen])))
    return max(scores, key=scores.get), scores


def main():
    parser = training_parser(__doc__, "exclone_appearance_training",
                             "where the training takes' frames are cached")
    parser.add_argument("--jobs", type=int, default=2, help="takes rendered or read at once")
    args = parser.parse_args()
    require_identities(args.identities, "make_appearance_model")
    if args.jobs < 1:
        sys.exit(f"make_appearance_model: --jobs must be at least 1, got {args.jobs}")
    # each take in its own process: Blender's scene is one per process
    with ProcessPoolExecutor(args.jobs, mp_context=get_context("spawn")) as pool:
        learn(pool, list(pool.map(render_take, repeat(args.work), TRAINING_IDENTITIES,
                                  repeat(args.identities))), args.identities)


def learn(pool, takes, identities_file):
    """Learns the map from the takes' frames (paths by take of TRAINING_IDENTITIES), reading
    them in `pool`'s processes, and writes it."""
    names = list(load_library().names)
    motion = load_tracker_model().expressions
    keys = [j for j, name in enumerate(names)
            if not name.startswith(EYE_KEY_PREFIX) and np.abs(motion[j]).max() >= MOVES_CM]
    solver = appearance.points_solver([names[j] for j in keys], motion[keys])
    tracked = list(pool.map(read_take, takes, repeat(solver)))
    recipes = [take_recipe(identity, names) for identity in TRAINING_IDENTITIES]
    seen = [np.all(np.isfinite(readings), axis=1) for readings, *_ in tracked]
    changes = [readings[ok] for (readings, *_), ok in zip(tracked, seen)]
    points = [read[ok] for (_, read, *_), ok in zip(tracked, seen)]
    weights = [recipe[0][ok][:, keys] for recipe, ok in zip(recipes, seen)]
    errors = [turn_errors(turns[ok], recipe[1][ok])
              for (_, _, _, turns, _), recipe, ok in zip(tracked, recipes, seen)]
    read = held_out_weights(changes, points, weights,
                            [(components, ridge) for components in COMPONENTS for ridge in RIDGES])
    scores = held_out_scores(read, weights)
    components, ridge = max(scores, key=scores.get)
    print("make_appearance_model: held-out correlation by components and ridge: " +
          ", ".join(f"{c} / {r}: {score:.3f}" for (c, r), score in scores.items()), flush=True)
    raw = read[components, ridge]
    from_neutral = [angles[ok] for (*_, angles), ok in zip(tracked, seen)]
    unmixing, by_turn, unmixed, band_errors = held_out_unmixing_by_turn(raw, weights,
                                                                        from_neutral)
    unmixing_errors = held_out_squared_errors({**unmixed, "by turn": by_turn}, weights)
    unmixing_scores = held_out_scores({**unmixed, "by turn": by_turn}, weights)
    print("make_appearance_model: held-out squared error (correlation) un-mixed by the penalty: "
          f"read {held_out_squared_errors({0: raw}, weights)[0]:.5f}, " +
          ", ".join(f"{r}: {unmixing_errors[r]:.5f} ({unmixing_scores[r]:.3f})"
                    for r in (*UNMIXING_RIDGES, "by turn")), flush=True)
    for b, errors_by_ridge in band_errors.items():
        print(f"make_appearance_model: turn band {b} (median {unmixing[0][b]:.1f} deg): held-out "
              "squared error by the penalty: " +
              ", ".join(f"{r}: {e:.5f}" for r, e in errors_by_ridge.items()), flush=True)
    turn_ridge, turn_scores = held_out_turn_ridge(by_turn, errors)
    print("make_appearance_model: held-out median turn error (deg) by the turn bias's ridge: " +
          ", ".join(f"{r}: {score:.3f}" for r, score in turn_scores.items()), flush=True)
    truths = [recipe[0] for recipe in recipes]
    share, share_scores = held_out_share(pool, takes, truths, changes, points, weights, keys,
                                         names, motion, (components, ridge, unmixing), raw,
                                         identities_file)
    print("make_appearance_model: held-out correlation by the appearance's share: " +
          ", ".join(f"{s}: {score:.3f}" for s, score in share_scores.items()), flush=True)
    learned = appearance.learn_appearance_map(np.vstack(changes), np.vstack(points),
                                              np.vstack(weights), [names[j] for j in keys],
                                              motion[keys], components, ridge)
    # the response and the turn's bias from what maps read of frames they were not learnt from
    turn_bias = appearance.learn_turn_bias(by_turn, errors, turn_ridge)
    appearance.write_appearance_map(replace(
        learned, share=share, turn_bias=turn_bias, response=appearance.learn_response(raw, weights),
        unmixing_turns=unmixing[0], unmixing_ridges=unmixing[1]))
    print(f"make_appearance_model: learnt from {sum(map(len, changes))} frames of "
          f"{len(TRAINING_IDENTITIES)} takes ({components} components, ridge {ridge}, un-mixing "
          f"ridges {unmixing[1]} at turns {tuple(round(t, 1) for t in unmixing[0])} deg, share "
          f"{share}, turn ridge {turn_ridge}); wrote "
          f"{APPEARANCE_MAP_FILE}")


if __name__ == "__main__":
    main()
