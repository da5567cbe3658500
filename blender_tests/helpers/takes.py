"""Known-answer takes shared by the tracking tests.

- the synthetic ICT take: the bundled ICT head posed with known expression weights and a known
  head rotation, sampled where the canonical face's 468 points lie on it, projected through a
  known camera with pixel noise (checks the solver, not the image models);
- the astronaut photograph (skimage, public domain) moved by known 2D motions.
"""
import functools
import time
from types import SimpleNamespace

import cv2
import numpy as np
from scipy.spatial.transform import Rotation
from skimage import data as skimage_data

from exclone_addon.core import data
from exclone_addon.core.library import load_library
from exclone_addon.core.tracker_model import locate_tracker_landmarks
from exclone_addon.core.tracking import (FRONTAL, Camera, ShapeFitter, calibrate_neutral,
                                         expression_shape_model)

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
