"""Known-answer takes shared by the tracking tests.

- the synthetic ICT take: the bundled ICT head posed with known expression weights and a known
  head rotation, sampled where the canonical face's 468 points lie on it, projected through a
  known camera with pixel noise (checks the solver, not the image models);
- the astronaut photograph (skimage, public domain) moved by known 2D motions;
- rendered takes: an ICT-topology head (the bundled one or an ICT identity) posed with known
  weights and head turns, rendered in background Blender by scripts/render_faces.py (needs bpy;
  cached in the temp directory), tracked through the image models by FaceTrackingSession.step.
"""
import functools
import hashlib
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
from scipy.spatial.transform import Rotation
from skimage import data as skimage_data

from exclone_addon.core import data
from exclone_addon.core.library import ARKIT_SPLIT, load_library
from exclone_addon.core.retarget import AvatarRig
from exclone_addon.core.session import FaceTrackingSession
from exclone_addon.core.tracker_model import locate_tracker_landmarks, read_tracker_locations
from exclone_addon.core.tracking import (FRONTAL, Camera, ShapeFitter, calibrate_neutral,
                                         expression_shape_model)

from blender_tests.helpers.frame_cache import cached_frames
from blender_tests.helpers.paths import REPO_ROOT, SHARED_DATA

sys.path.insert(0, str(REPO_ROOT / "scripts"))   # render_faces (rendered takes only)

FRAMES = 200
CALIBRATION_FRAMES = 30      # a neutral face, the head turning (one second at 30 fps)
FPS = 30.0
IMAGE_SIZE = (640, 480)


@functools.lru_cache(maxsize=1)
def ict_rig():
    """The ICT library with the canonical face located on its skin (the registration the shipped
    tracker model is made from, run afresh), and the tracker's model."""
    library = load_library()
    canonical = data.canonical_face()
    locations = locate_tracker_landmarks(library)
    neutral = locations.sample(library.mesh.vertices)
    deltas = locations.sample(library.deltas)
    model = expression_shape_model(canonical.vertices, neutral, deltas)
    motion = np.sqrt((deltas ** 2).sum(axis=2).mean(axis=1))
    active = np.argsort(-motion)[:10]          # the 10 shapes that move the landmarks most
    return SimpleNamespace(library=library, canonical=canonical, locations=locations,
                           neutral=neutral, deltas=deltas, model=model, active=active)


@functools.lru_cache(maxsize=3)
def synthetic_take(outlier_fraction=0.0, shapes=None, noise_px=1.0, seed=5):
    """200 frames: known weights (smooth, in 0..1) of `shapes` (names; default the 10 most
    active) and a known head rotation (up to 25 deg about one axis, 30 deg overall)."""
    rig = ict_rig()
    rng = np.random.default_rng(seed)
    t = np.arange(FRAMES) / FPS
    weights = np.zeros((FRAMES, len(rig.deltas)))
    active = rig.active if shapes is None else [rig.library.names.index(n) for n in shapes]
    for j in active:
        freq, phase = rng.uniform(0.2, 0.8, 2), rng.uniform(0, 2 * np.pi, 2)
        weights[:, j] = np.clip(0.5 + 0.35 * np.sin(2 * np.pi * freq[0] * t + phase[0])
                                + 0.25 * np.sin(2 * np.pi * freq[1] * t + phase[1]), 0.0, 1.0)
    weights[:CALIBRATION_FRAMES] = 0.0
    angles = np.column_stack((25 * np.sin(2 * np.pi * 0.3 * t), 18 * np.sin(2 * np.pi * 0.21 * t + 1),
                              10 * np.sin(2 * np.pi * 0.17 * t + 2)))
    c = t[:CALIBRATION_FRAMES]
    angles[:CALIBRATION_FRAMES] = np.column_stack((15 * np.sin(2 * np.pi * c), 10 * np.sin(4 * np.pi * c),
                                                   0 * c))
    rotations = Rotation.from_euler("yxz", angles, degrees=True)      # in camera space
    camera = Camera.from_image_size(*IMAGE_SIZE)
    centre = rig.neutral.mean(axis=0)
    points = np.empty((FRAMES, len(rig.neutral), 2))
    outliers = np.zeros((FRAMES, len(rig.neutral)), dtype=bool)
    for k in range(FRAMES):
        face = rig.neutral + np.tensordot(weights[k], rig.deltas, axes=1) - centre
        camera_points = (rotations[k] * FRONTAL).apply(face) + [1.0, -2.0, 55.0]
        points[k] = camera.project(camera_points) + rng.normal(0.0, noise_px, (len(face), 2))
        if outlier_fraction:
            ids = rng.choice(len(face), int(round(outlier_fraction * len(face))), replace=False)
            low, high = points[k].min(axis=0), points[k].max(axis=0)
            margin = 0.2 * (high - low)
            points[k, ids] = rng.uniform(low - margin, high + margin, (len(ids), 2))
            outliers[k, ids] = True
    return SimpleNamespace(points=points, weights=weights, rotations=rotations, camera=camera,
                           outliers=outliers, active=np.array(active))


@functools.lru_cache(maxsize=3)
def tracked_take(outlier_fraction=0.0, shapes=None):
    """The take through calibration (first second) and the per-frame fit, with fit times."""
    rig, take = ict_rig(), synthetic_take(outlier_fraction, shapes)
    fitter = ShapeFitter(rig.model, take.camera)
    start = time.perf_counter()
    neutral, actor_fitter, fits = calibrate_neutral(fitter, take.points[:CALIBRATION_FRAMES])
    calibration_s = time.perf_counter() - start
    times = []
    for points in take.points[CALIBRATION_FRAMES:]:
        start = time.perf_counter()
        fits.append(actor_fitter.fit(points, previous=fits[-1]))
        times.append(time.perf_counter() - start)
    return SimpleNamespace(neutral=neutral, fitter=actor_fitter, fits=fits,
                           calibration_s=calibration_s, fit_ms=1000 * np.array(times))


def rotation_errors_deg(take, fits):
    """Head rotation relative to frame 0, estimated vs true, per frame (degrees)."""
    ref_est, ref_true = fits[0].rotation, take.rotations[0]
    return np.array([np.degrees(((f.rotation * ref_est.inv()).inv()
                                 * take.rotations[k] * ref_true.inv()).magnitude())
                     for k, f in enumerate(fits)])


# The astronaut's face centre in skimage's 512x512 photograph, moved to the 640x480 frame's centre.
FACE_CENTRE = (224.0, 135.0)
ASTRONAUT_FRAMES = 60


@functools.lru_cache(maxsize=1)
def astronaut():
    return cv2.cvtColor(skimage_data.astronaut(), cv2.COLOR_RGB2BGR)


def astronaut_motion(k):
    """Frame k's known 2x3 motion of the photograph: a turn of up to 15 degrees, scale 0.8-1.2,
    shifts of up to 80 px (peak speed about 250 px/s at 30 fps)."""
    t = k / ASTRONAUT_FRAMES
    matrix = cv2.getRotationMatrix2D(FACE_CENTRE, 15 * np.sin(2 * np.pi * t),
                                     1 + 0.2 * np.sin(2 * np.pi * 1.5 * t + 1))
    matrix[:, 2] += (320 - FACE_CENTRE[0] + 80 * np.sin(2 * np.pi * t + 0.5),
                     240 - FACE_CENTRE[1] + 50 * np.sin(4 * np.pi * t))
    return matrix


def astronaut_frame(k):
    return cv2.warpAffine(astronaut(), astronaut_motion(k), (640, 480), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REPLICATE)


# -- rendered takes: faces rendered in background Blender, tracked through the image models -------

# The shapes a rendered take drives (ARKit units; a unit ICT splits in halves drives both), the
# eyes left to the eye tests.
DRIVEN = ("jawOpen", "mouthSmile_L", "mouthSmile_R", "mouthFrown_L", "mouthFrown_R", "mouthPucker",
          "mouthFunnel", "cheekPuff", "browInnerUp", "browDown_L", "browDown_R", "browOuterUp_L",
          "browOuterUp_R", "noseSneer_L", "noseSneer_R", "mouthStretch_L", "mouthStretch_R")
RENDER_DISTANCE_CM = 50.0      # the head's centre from the camera: a face about 200 px wide
BUMP_FRAMES = 20               # each shape rises and falls over this many frames
BUMP_SPACING = 10              # a new shape starts every this many frames (two overlap)
RENDER_CACHE = Path(tempfile.gettempdir()) / "exclone_rendered_takes"
RENDER_VERSION = 2             # bump when the renderer or a take's recipe changes
# The ICT identity (the identity model's weights for this seed, identity_head) the rendered and
# eye takes track beside the bundled head.
OTHER_IDENTITY = 7
# A wide calibration: the actor holds a neutral face and turns the head slowly over the range a
# take uses (what a product can ask: "hold a neutral face and turn your head"), yaw +-30 deg and
# pitch +-20 deg in a figure of eight over this many frames (3 s at 30 fps).
WIDE_CALIBRATION_FRAMES = 90
CALIBRATIONS = ("small", "wide")


def unit_keys(names, unit):
    """The library keys an ARKit unit drives: itself, or its two ICT halves."""
    halves = ARKIT_SPLIT.get(unit, (unit,))
    return [names.index(name) for name in halves]


def calibration_length(calibration="small"):
    """The frames a calibration of this kind reads (CALIBRATIONS)."""
    if calibration not in CALIBRATIONS:
        raise ValueError(f"calibration {calibration!r} is not one of {CALIBRATIONS}")
    return WIDE_CALIBRATION_FRAMES if calibration == "wide" else CALIBRATION_FRAMES


def take_recipe(kind, frames=None, seed=3, calibration="small"):
    """(weights of each DRIVEN unit (T, U), head turn in camera axes as yxz Euler degrees (T, 3)).

    kind: "moving" (the units in overlapping bumps, the head turning up to 25 deg about one axis),
    "still" (the same bumps, the head still) or "turning" (a neutral face turning up to 30 deg).
    The first calibration_length(calibration) frames hold a neutral face: turning a little
    ("small": 10 deg yaw, 6 deg pitch over one second) or over the take's range ("wide": yaw
    +-30 deg, pitch +-20 deg over three seconds); the take after them is the same either way.
    """
    rng = np.random.default_rng(seed)
    calibration_frames = calibration_length(calibration)
    count = calibration_frames + BUMP_SPACING * len(DRIVEN) + BUMP_FRAMES
    frames = frames or count
    t = np.arange(frames) / FPS
    weights = np.zeros((frames, len(DRIVEN)))
    if kind != "turning":
        bump = 0.5 - 0.5 * np.cos(2 * np.pi * np.arange(BUMP_FRAMES) / (BUMP_FRAMES - 1))
        for u in range(len(DRIVEN)):
            start = calibration_frames + BUMP_SPACING * u
            stop = min(start + BUMP_FRAMES, frames)
            if start < frames:
                weights[start:stop, u] = rng.uniform(0.6, 1.0) * bump[:stop - start]
    if kind == "still":
        angles = np.zeros((frames, 3))
    else:
        # the turns start from zero where calibration ends (it ends near zero too): a head
        # cannot jump 30 deg between two frames (version 1 did, and every filter lags a jump)
        size = 30.0 if kind == "turning" else 25.0
        since = t - calibration_frames / FPS
        angles = np.column_stack((size * np.sin(2 * np.pi * 0.23 * since),
                                  0.7 * size * np.sin(2 * np.pi * 0.17 * since),
                                  0.4 * size * np.sin(2 * np.pi * 0.13 * since)))
    c = t[:calibration_frames]
    if calibration == "wide":
        period = WIDE_CALIBRATION_FRAMES / FPS
        angles[:calibration_frames] = np.column_stack((30 * np.sin(2 * np.pi * c / period),
                                                       20 * np.sin(4 * np.pi * c / period), 0 * c))
    else:
        angles[:calibration_frames] = small_calibration_turn(calibration_frames)
    return weights, angles


def small_calibration_turn(frames=CALIBRATION_FRAMES):
    """(frames, 3) the head's turn (camera axes, yxz Euler degrees) while a session's one-second
    calibration reads a neutral face: 10 deg of yaw and 6 of pitch, as an actor settles."""
    c = np.arange(frames) / FPS
    return np.column_stack((10 * np.sin(2 * np.pi * c), 6 * np.sin(4 * np.pi * c), 0 * c))


def identity_head(identity):
    """(neutral vertices, expression deltas, names, parts) of an ICT-topology head: the bundled
    library (identity None) or the ICT identity model's face for a seed (weights N(0, 1) on its
    30 modes, as ICT-FaceKit's randomize_identity), wearing the library's expressions."""
    library = load_library()
    vertices = library.mesh.vertices
    if identity is not None:
        with np.load(SHARED_DATA / "ict-facekit" / "identities.npz") as stored:
            modes = stored["deltas"].astype(np.float64)
        coefficients = np.random.default_rng(identity).standard_normal(len(modes))
        vertices = vertices + np.tensordot(coefficients, modes, axes=1)
    return vertices, library.deltas, list(library.names), library.parts


def _take_key(kind, identity, frames, seed, calibration="small", light_turn=None):
    text = f"v{RENDER_VERSION}-{kind}-{identity}-{frames}-{seed}-{IMAGE_SIZE}-{RENDER_DISTANCE_CM}"
    if calibration != "small":      # the small calibration's takes keep their cache keys
        text += f"-{calibration}-calibration"
    if light_turn is not None:      # and those lit from the camera's side
        text += f"-light-{light_turn}"
    return hashlib.sha1(text.encode()).hexdigest()[:16]


# A light from one side: Workbench's default studio light fixed in the scene and turned 1.2 rad
# (69 deg) about the vertical, as a window beside the actor lights a face (the appearance map's
# training takes are lit from the camera's side).
SIDE_LIGHT_TURN = 1.2


def rendered_take(kind="moving", identity=None, frames=None, seed=3, calibration="small",
                  light_turn=None):
    """A take rendered in background Blender (needs bpy), cached on disk by its parameters:
    frames (list of PNG paths), truth (library-key weights (T, E)), unit weights (T, U), the
    head's model -> camera rotations, translations, the camera, render seconds per frame
    (CPU time, 0 when read from the cache) and how many of its first frames are calibration's.
    light_turn: render_faces.FaceRenderer's (None: lit from the camera's side)."""
    weights, angles = take_recipe(kind, frames, seed, calibration)
    vertices, deltas, names, parts = identity_head(identity)
    truth = np.zeros((len(weights), len(names)))
    for u, unit in enumerate(DRIVEN):
        truth[:, unit_keys(names, unit)] = weights[:, u:u + 1]
    rotations = Rotation.from_euler("yxz", angles, degrees=True) * FRONTAL
    locations = read_tracker_locations()
    centre = locations.sample(vertices).mean(axis=0)
    translation = np.array([0.0, 0.0, RENDER_DISTANCE_CM])
    paths, seconds = cached_frames(
        RENDER_CACHE / _take_key(kind, identity, len(weights), seed, calibration, light_turn),
        len(weights),
        lambda paths: _render_take(paths, vertices, deltas, parts, truth, rotations, translation,
                                   centre, locations, light_turn))
    return SimpleNamespace(frames=paths, truth=truth, unit_weights=weights, names=names,
                           rotations=rotations, translation=translation, kind=kind,
                           camera=Camera.from_image_size(*IMAGE_SIZE), render_s=seconds,
                           vertices=vertices, deltas=deltas,
                           calibration_frames=calibration_length(calibration))


def _render_take(paths, vertices, deltas, parts, truth, rotations, translation, centre,
                 locations, light_turn):
    """Renders every frame to `paths`; returns the CPU seconds per frame."""
    import render_faces      # needs bpy: imported only when a take is rendered
    colours = render_faces.vertex_colours(vertices, parts, locations.sample(vertices))
    renderer = render_faces.FaceRenderer(
        render_faces.rendered_triangles(load_library().mesh.triangles(), parts), colours,
        IMAGE_SIZE, light_turn=light_turn)
    return render_frames(renderer, paths, vertices, deltas, truth, rotations, translation, centre)


def render_frames(renderer, paths, vertices, deltas, truth, rotations, translation, centre):
    """Renders frame k to paths[k] (render_faces.FaceRenderer `renderer`): the head's vertices
    wearing the weights truth[k] of `deltas`, turned by rotations[k] about `centre` and moved to
    `translation`; returns the CPU seconds per frame."""
    import render_faces      # needs bpy: imported only when a take is rendered
    start = time.process_time()
    for k, path in enumerate(paths):
        posed = vertices + np.tensordot(truth[k], deltas, axes=1)
        renderer.render(render_faces.head_pose_points(posed, rotations[k], translation, centre),
                        path)
    return (time.process_time() - start) / len(paths)


def ict_avatar(take):
    """The take's own head as the avatar (the ideal answer is the truth): its library keys
    sampled where the tracker's points lie on it (the shipped locations: same topology)."""
    return AvatarRig.from_locations(take.vertices, take.deltas, take.names, read_tracker_locations())


# A webcam's frames: sensor noise of this standard deviation (of 255; each pixel's and frame's
# own, as a dim room's webcam gives), then MJPEG compression at this quality.
WEBCAM_NOISE = 10.0
WEBCAM_JPEG_QUALITY = 80


def through_a_webcam(take, noise=WEBCAM_NOISE, quality=WEBCAM_JPEG_QUALITY, seed=0):
    """The take with its rendered frames as a webcam would deliver them (noise, then JPEG),
    cached beside them."""
    source = take.frames[0].parent
    key = hashlib.sha1(f"{source.name}-{noise}-{quality}-{seed}".encode()).hexdigest()[:16]

    def degrade(paths):
        rng = np.random.default_rng(seed)
        for frame, path in zip(take.frames, paths):
            image = cv2.imread(str(frame)).astype(np.float64)
            noisy = np.clip(np.rint(image + rng.normal(0.0, noise, image.shape)), 0, 255)
            _, jpeg = cv2.imencode(".jpg", noisy.astype(np.uint8),
                                   [cv2.IMWRITE_JPEG_QUALITY, quality])
            cv2.imwrite(str(path), cv2.imdecode(jpeg, cv2.IMREAD_COLOR))
        return 0.0

    paths, _ = cached_frames(RENDER_CACHE / f"webcam-{key}", len(take.frames), degrade)
    return SimpleNamespace(**{**vars(take), "frames": paths})


def track_rendered(take, avatar=None, tracker_model=None, appearance=True):
    """The take's frames through FaceTrackingSession.step (what a camera feeds): weights by
    library key (T, E; NaN before calibration or without a face), model -> camera rotations
    (None without a face), and the step's milliseconds. appearance: as the session's."""
    session = FaceTrackingSession(avatar=avatar if avatar is not None else ict_avatar(take),
                                  camera=take.camera, calibration_frames=take.calibration_frames,
                                  tracker_model=tracker_model, appearance=appearance)
    weights = np.full(take.truth.shape, np.nan)
    rotations, step_ms = [], []
    index = {name: j for j, name in enumerate(take.names)}
    for k, path in enumerate(take.frames):
        start = time.perf_counter()
        result = session.step(cv2.imread(str(path)), k / FPS)
        step_ms.append(1000 * (time.perf_counter() - start))
        rotations.append(result.rotation if result.found else None)
        if result.found and result.weights is not None:
            for name, value in result.weights.items():
                if name in index:
                    weights[k, index[name]] = value
    return SimpleNamespace(weights=weights, rotations=rotations, step_ms=np.array(step_ms),
                           session=session)


def track_true_points(take, tracker_model=None):
    """The known answer past the image models: the take's own head, posed as rendered, sampled
    at the tracker's points (the shipped locations) and projected by the take's camera, through
    FaceTrackingSession.step_landmarks onto the same head. Weights as track_rendered's."""
    locations = read_tracker_locations()
    centre = locations.sample(take.vertices).mean(axis=0)
    session = FaceTrackingSession(avatar=ict_avatar(take), camera=take.camera,
                                  calibration_frames=take.calibration_frames,
                                  tracker_model=tracker_model)
    weights = np.full(take.truth.shape, np.nan)
    index = {name: j for j, name in enumerate(take.names)}
    for k in range(len(take.truth)):
        posed = locations.sample(take.vertices + np.tensordot(take.truth[k], take.deltas, axes=1))
        points = take.camera.project(take.rotations[k].apply(posed - centre) + take.translation)
        result = session.step_landmarks(points, k / FPS, image_size=IMAGE_SIZE)
        for name, value in (result.weights or {}).items():
            weights[k, index[name]] = value
    return SimpleNamespace(weights=weights, session=session)


def unit_scores(take, tracked):
    """Per DRIVEN unit over the frames after calibration: (correlation, mean absolute error);
    a split unit's estimate is the mean of its halves."""
    frames = slice(take.calibration_frames, None)
    scores = {}
    for u, unit in enumerate(DRIVEN):
        keys = unit_keys(take.names, unit)
        estimate = tracked.weights[frames][:, keys].mean(axis=1)
        truth = take.unit_weights[frames, u]
        scores[unit] = (float(np.corrcoef(estimate, truth)[0, 1]),
                        float(np.abs(estimate - truth).mean()))
    return scores


def largest_false_weight(take, tracked, only="", but=None):
    """The largest weight after calibration on a take whose face stays neutral, and its key's
    name, over the keys whose names start with `only` (default: every key) and not with `but`."""
    keys = [j for j, name in enumerate(take.names)
            if name.startswith(only) and not (but and name.startswith(but))]
    weights = tracked.weights[take.calibration_frames:, keys]
    k, j = np.unravel_index(np.nanargmax(weights), weights.shape)
    return float(weights[k, j]), take.names[keys[j]]


# The head-rotation target: the error's median and max (degrees), every axis the head
# turns about read within 5% of its size.
ROTATION_TARGET = (1.5, 3.0, (0.95, 1.05))


def assert_pose_reaches_target(take, tracked):
    assert_pose_as_measured(take, tracked, *ROTATION_TARGET)


def assert_pose_as_measured(take, tracked, most_median, most_max, slope_range):
    """The rotation error (pose_errors) within a median and a max (degrees), each axis the head
    turns about read at a slope within slope_range (low, high)."""
    errors, slopes = pose_errors(take, tracked)
    assert np.median(errors) <= most_median and errors.max() <= most_max, (np.median(errors),
                                                                           errors.max())
    turned = np.isfinite(slopes)
    assert np.all((slopes[turned] >= slope_range[0]) & (slopes[turned] <= slope_range[1])), slopes


def pose_errors(take, tracked):
    """Head-rotation errors after calibration: (per-frame error in degrees (T,), per-axis slope
    of the estimated against the true turn (x pitch, y yaw, z roll, camera axes)).

    The tracker's model frame differs from the head's by a constant rotation: the one that best
    aligns the estimates to the truth (their mean difference) is taken out first."""
    ks = [k for k in range(take.calibration_frames, len(take.frames)) if tracked.rotations[k] is not None]
    estimated = Rotation.concatenate([tracked.rotations[k] for k in ks])
    true = take.rotations[ks]
    offset = (true.inv() * estimated).mean()
    turn_est = estimated * offset.inv() * FRONTAL.inv()
    turn_true = true * FRONTAL.inv()
    errors = np.degrees((turn_est * turn_true.inv()).magnitude())
    a, b = turn_true.as_rotvec(), turn_est.as_rotvec()
    slopes = np.array([np.polyfit(a[:, i], b[:, i], 1)[0] if np.ptp(a[:, i]) > 0.02 else np.nan
                       for i in range(3)])     # an axis the head does not turn about: NaN
    return errors, slopes
