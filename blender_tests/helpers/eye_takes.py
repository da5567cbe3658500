"""An eye take: an ICT-topology head (the bundled one or an ICT identity) blinking
(eyeBlink_L/R, 150 ms blinks among them) and looking about (its eyeballs turned by known angles,
up to 20 degrees), facing the camera or turning (up to 25 degrees of yaw), rendered in background
Blender by scripts/render_faces.py and cached on disk by its recipe.
"""
import hashlib
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from scipy.spatial.transform import Rotation

from exclone_addon.core.library import load_library
from exclone_addon.core.tracker_model import read_tracker_locations
from exclone_addon.core.tracking import FRONTAL, Camera
from blender_tests.helpers.frame_cache import cached_frames
from blender_tests.helpers.takes import identity_head, small_calibration_turn
from blender_tests.helpers.paths import REPO_ROOT

sys.path.insert(0, str(REPO_ROOT / "scripts"))   # render_faces (rendering only)

FPS = 30.0
CALIBRATION_FRAMES = 30
EYE_FRAMES = 240
IMAGE_SIZE = (640, 480)
DISTANCE_CM = 45.0
GAZE_DEG = 20.0
# (first frame, frames): blinks of 4 and 5 frames last 133-167 ms at 30 fps
BLINKS = ((50, 5), (82, 4), (110, 8), (140, 5), (172, 4), (205, 6))
EYE_CACHE = Path(tempfile.gettempdir()) / "exclone_eye_takes"
EYE_TAKE_VERSION = 1      # bump when the recipe or the renderer changes
# The turning take's head: the largest turn about y, x, z (camera axes, degrees), reached slowly
# (periods of 8-14 s), from a second's calibration turning a little (takes.small_calibration_turn).
HEAD_TURN_DEG = (25.0, 15.0, 8.0)


def blink_profile(frames):
    """A blink's weights over its frames: closing, closed, opening (peak 1)."""
    phase = np.sin(np.pi * (np.arange(frames) + 0.5) / frames)
    return np.clip(1.6 * phase, 0.0, 1.0)


def eye_recipe(frames=EYE_FRAMES):
    """(blink weight (T,), gaze yaw (T,), gaze pitch (T,) in degrees): yaw positive towards the
    subject's left, pitch positive up; the first CALIBRATION_FRAMES are neutral, looking ahead."""
    t = (np.arange(frames) - CALIBRATION_FRAMES) / FPS
    yaw = GAZE_DEG * np.sin(2 * np.pi * 0.31 * t)
    pitch = GAZE_DEG * np.sin(2 * np.pi * 0.19 * t + 0.7) - GAZE_DEG * np.sin(0.7)
    pitch = np.clip(pitch, -GAZE_DEG, GAZE_DEG)
    yaw[:CALIBRATION_FRAMES] = pitch[:CALIBRATION_FRAMES] = 0.0
    blink = np.zeros(frames)
    for start, length in BLINKS:
        if start + length <= frames:
            blink[start:start + length] = blink_profile(length)
    return blink, yaw, pitch


def head_turns(frames=EYE_FRAMES, turning=False):
    """The head's turn in each frame (model -> camera): facing the camera, or turning."""
    if not turning:
        return Rotation.concatenate([FRONTAL] * frames)
    t = (np.arange(frames) - CALIBRATION_FRAMES) / FPS
    ease = np.clip(t, 0.0, 1.0)[:, None]          # from the calibration's turn over a second
    angles = ease * HEAD_TURN_DEG * np.sin(2 * np.pi * np.array([0.13, 0.09, 0.07]) * t[:, None]
                                           + [0.5, 2.0, 0.0])
    angles[:CALIBRATION_FRAMES] = small_calibration_turn(CALIBRATION_FRAMES)
    return Rotation.from_euler("yxz", angles, degrees=True) * FRONTAL


def turned_eyes(vertices, eyeballs, yaw_deg, pitch_deg):
    """The head's vertices with both eyeballs (vertex range `eyeballs`) turned about their
    centres: yaw about +Y (towards +X, the subject's left), then pitch up."""
    turned = vertices.copy()
    start, stop = eyeballs
    balls = turned[start:stop]
    rotation = Rotation.from_euler("yx", [yaw_deg, -pitch_deg], degrees=True)
    for side in (balls[:, 0] < 0, balls[:, 0] >= 0):
        points = balls[side]
        centre = 0.5 * (points.min(axis=0) + points.max(axis=0))
        balls[side] = rotation.apply(points - centre) + centre
    turned[start:stop] = balls
    return turned


def _key(frames, turning, identity):
    text = f"v{EYE_TAKE_VERSION}-{frames}-{IMAGE_SIZE}-{DISTANCE_CM}-{BLINKS}-{GAZE_DEG}"
    if turning:
        text += f"-turning{HEAD_TURN_DEG}-calibration2"
    if identity is not None:      # the bundled head's takes keep their cache keys
        text += f"-identity{identity}"
    return hashlib.sha1(text.encode()).hexdigest()[:16]


def rendered_eye_take(frames=EYE_FRAMES, turning=False, identity=None):
    """The take's frames (PNG paths), its truth (blink, yaw, pitch), the head (neutral vertices,
    expression deltas, key names: takes.identity_head of `identity`, None for the bundled head),
    the camera and the CPU seconds a frame took to render (0 when read from the cache); the head
    facing the camera, or turning (head_turns)."""
    blink, yaw, pitch = eye_recipe(frames)
    rotations = head_turns(frames, turning)
    vertices, deltas, names, parts = identity_head(identity)
    paths, seconds = cached_frames(
        EYE_CACHE / _key(frames, turning, identity), frames,
        lambda paths: _render(paths, vertices, deltas, names, parts, blink, yaw, pitch, rotations))
    return SimpleNamespace(frames=paths, blink=blink, yaw=yaw, pitch=pitch, turning=turning,
                           identity=identity, vertices=vertices, deltas=deltas, names=names,
                           camera=Camera.from_image_size(*IMAGE_SIZE), render_s=seconds)


def _render(paths, vertices, deltas, names, parts, blink, yaw, pitch, rotations):
    import render_faces      # needs bpy
    located = read_tracker_locations().sample(vertices)
    renderer = render_faces.FaceRenderer(
        render_faces.rendered_triangles(load_library().mesh.triangles(), parts),
        render_faces.vertex_colours(vertices, parts, located), IMAGE_SIZE)
    blinks = [names.index(name) for name in ("eyeBlink_L", "eyeBlink_R")]
    closing = deltas[blinks].sum(axis=0)
    centre = located.mean(axis=0)
    translation = np.array([0.0, 0.0, DISTANCE_CM])
    start = time.process_time()
    for k, path in enumerate(paths):
        posed = turned_eyes(vertices + blink[k] * closing, parts["eyeballs"], yaw[k], pitch[k])
        renderer.render(render_faces.head_pose_points(posed, rotations[k], translation, centre),
                        path)
    return (time.process_time() - start) / len(paths)
