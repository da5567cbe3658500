"""Write exclone_addon/data/tracker_model.npz, the tracker's shape model (core.tracker_model):

1. where the canonical face's 468 points lie on the bundled ICT-FaceKit face (a registration,
   about 5 s): the avatar's side of retargeting locates them there;
2. what FaceMesh reports for those points (needs bpy and ICT-FaceKit's identity model): ICT
   identities (not the ones the tests' rendered takes use) wearing random library expressions,
   turned up to 35 deg, rendered in background Blender at 640x480 (about 0.35 CPU s a frame,
   cached in --work), and read by FaceMesh as the session reads a camera frame; from those
   points and the known truth, core.tracker_model.learn_tracker_model fits the model's neutral,
   each expression's point motion and each point's slide with the head's turn;
3. what the iris model reads of the same frames' eyes (cropped from FaceMesh's points, as the
   session does): core.tracker_model.learn_eye_slide fits how the eyes' frontal reading slides
   with the head's turn;
4. the model's fit on those frames, and what it still reads wrongly of the head's turn
   (core.tracker_model.learn_pose_bias).

Run it after changing the bundled library, the canonical face, the cloning engine or the image
models; blender_tests/core/test_live.py checks the located points are current.

    .venv/bin/python scripts/make_tracker_model.py [--work DIR] [--identities FILE]
"""
import argparse
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from exclone_addon.core import eyes, face_models  # noqa: E402
from exclone_addon.core.data import TRACKER_MODEL_FILE  # noqa: E402
from exclone_addon.core.library import load_library  # noqa: E402
from exclone_addon.core.tracker_model import (TrackerModel, TrainingFrames,  # noqa: E402
                                              learn_eye_slide, learn_pose_bias,
                                              learn_tracker_model, locate_tracker_landmarks,
                                              write_tracker_model)
from exclone_addon.core.tracking import FRONTAL, Camera  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
IDENTITIES = REPO.parent / "shared" / "data" / "ict-facekit" / "identities.npz"
# ICT identity seeds to learn from: the tests' rendered takes use the bundled face and seed 7.
TRAINING_IDENTITIES = tuple(range(101, 109))
FRAMES_PER_IDENTITY = 120
IMAGE_SIZE = (640, 480)
# Head turns (camera axes, degrees: about y, x, z) drawn uniformly within these; the face 40-60 cm
# from the camera, up to 4 cm off its axis.
TURN_DEG = (35.0, 25.0, 15.0)
NEUTRAL_SHARE = 0.25          # frames with a neutral face; the others wear 1-3 keys at 0.3-1
RECIPE_VERSION = 1


def training_recipe(identity, names, frames=FRAMES_PER_IDENTITY):
    """(weights (T, E), rotations model -> camera, translations (T, 3), skin tint) of one
    identity's frames, from a generator seeded by the identity."""
    rng = np.random.default_rng(1000 + identity)
    weights = np.zeros((frames, len(names)))
    for k in range(frames):
        if rng.uniform() < NEUTRAL_SHARE:
            continue
        keys = rng.choice(len(names), rng.integers(1, 4), replace=False)
        weights[k, keys] = rng.uniform(0.3, 1.0, len(keys))
    angles = rng.uniform(-1.0, 1.0, (frames, 3)) * TURN_DEG
    rotations = Rotation.from_euler("yxz", angles, degrees=True) * FRONTAL
    translations = np.column_stack((rng.uniform(-4, 4, frames), rng.uniform(-3, 3, frames),
                                    rng.uniform(40, 60, frames)))
    return weights, rotations, translations, rng.uniform(0.75, 1.15)


def identity_vertices(library, identity, identities_file):
    with np.load(identities_file) as stored:
        modes = stored["deltas"].astype(np.float64)
    coefficients = np.random.default_rng(identity).standard_normal(len(modes))
    return library.mesh.vertices + np.tensordot(coefficients, modes, axes=1)


def render_identity(folder, library, vertices, recipe, locations, studio_light="Default"):
    """Renders one identity's frames into `folder` (skipped when they are there) under one of
    Workbench's studio lights (render_faces.STUDIO_LIGHTS)."""
    paths = [folder / f"frame_{k:04d}.png" for k in range(len(recipe[0]))]
    if all(path.is_file() for path in paths):
        return paths
    import render_faces     # needs bpy
    weights, rotations, translations, tint = recipe
    colours = render_faces.vertex_colours(vertices, library.parts, locations.sample(vertices))
    start, stop = library.parts["face"]
    colours[start:stop] *= tint
    renderer = render_faces.FaceRenderer(
        render_faces.rendered_triangles(library.mesh.triangles(), library.parts), colours,
        IMAGE_SIZE, studio_light=studio_light)
    centre = locations.sample(vertices).mean(axis=0)
    folder.mkdir(parents=True, exist_ok=True)
    for k, path in enumerate(paths):
        posed = vertices + np.tensordot(weights[k], library.deltas, axes=1)
        renderer.render(rotations[k].apply(posed - centre) + translations[k], path)
    return paths


def facemesh_points(paths, detector, landmarker):
    """(T, 468, 3) FaceMesh's points on each frame as a tracking session reads them (the region
    from a detection, then twice from the points); NaN where no face is found."""
    points = np.full((len(paths), face_models.NUM_LANDMARKS, 3), np.nan)
    for k, path in enumerate(paths):
        image = cv2.imread(str(path))
        detections = detector.detect_any_size(image)
        if not detections:
            continue
        found, presence = landmarker.landmarks(image, face_models.roi_from_detection(detections[0]))
        for _ in range(2):
            if presence < face_models.FACE_PRESENCE_THRESHOLD:
                break
            found, presence = landmarker.landmarks(image, face_models.roi_from_landmarks(found))
        if presence >= face_models.FACE_PRESENCE_THRESHOLD:
            points[k] = found
    return points


def eye_measures(paths, points, iris):
    """(T, 2, eyes.READING_MEASURES) the iris model's reading of each frame's eyes, cropped
    where FaceMesh's `points` (T, 468, 3) put them; NaN where no face was found."""
    measures = np.full((len(paths), 2, eyes.READING_MEASURES), np.nan)
    for k, path in enumerate(paths):
        if np.all(np.isfinite(points[k])):
            found = iris.eyes(cv2.imread(str(path)), points[k])
            measures[k] = eyes.reading_measures(eyes.read_eyes(found))
    return measures


def training_frames(work, identities_file, locations):
    library = load_library()
    detector, landmarker = face_models.FaceDetector(), face_models.FaceLandmarker()
    iris = face_models.IrisLandmarker()
    parts = []
    for identity in TRAINING_IDENTITIES:
        folder = work / f"v{RECIPE_VERSION}-identity{identity}"
        cached = folder / "facemesh.npy"
        vertices = identity_vertices(library, identity, identities_file)
        recipe = training_recipe(identity, library.names)
        if cached.is_file():
            points = np.load(cached)
        else:
            start = time.time()
            paths = render_identity(folder, library, vertices, recipe, locations)
            points = facemesh_points(paths, detector, landmarker)
            np.save(cached, points)
            print(f"make_tracker_model: identity {identity}: {len(paths)} frames in "
                  f"{time.time() - start:.0f} s", flush=True)
        cached_eyes = folder / "eyes.npy"
        if cached_eyes.is_file():
            measures = np.load(cached_eyes)
        else:
            paths = [folder / f"frame_{k:04d}.png" for k in range(len(points))]
            measures = eye_measures(paths, points, iris)
            np.save(cached_eyes, measures)
        weights, rotations, translations, _ = recipe
        centre = locations.sample(vertices).mean(axis=0)
        parts.append(TrainingFrames(
            points=points, weights=weights, rotations=rotations,
            translations=translations - rotations.apply(centre),
            neutral=locations.sample(vertices), eyes=measures))
    return parts, library


def training_parser(doc, work_folder, work_help):
    """A build script's arguments: --work (`work_folder` in the temp directory by default) and
    --identities; `doc`'s first paragraph describes it."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / work_folder,
                        help=work_help)
    parser.add_argument("--identities", type=Path, default=IDENTITIES,
                        help="ICT-FaceKit's identity model (identities.npz)")
    return parser


def require_identities(path, script):
    """Ends `script` in one line when ICT-FaceKit's identity model is not at `path`."""
    if not path.is_file():
        sys.exit(f"{script}: {path} is missing (ICT-FaceKit's identity model)")


def main():
    parser = training_parser(__doc__, "exclone_tracker_training",
                             "where the training renders and FaceMesh's points are cached")
    args = parser.parse_args()
    require_identities(args.identities, "make_tracker_model")
    sys.path.insert(0, str(REPO / "scripts"))     # render_faces
    locations = locate_tracker_landmarks()
    frames, library = training_frames(args.work, args.identities, locations)
    camera = Camera.from_image_size(*IMAGE_SIZE)
    learned = learn_tracker_model(locations, frames, library, camera)
    learned["eye_pose_offsets"] = learn_eye_slide(frames, library.names, camera)
    # the bias of the model as it ships (its arrays stored in single precision)
    shipped = {key: value.astype(np.float32).astype(np.float64) for key, value in learned.items()}
    learned["pose_bias"] = learn_pose_bias(TrackerModel.from_learned(shipped), frames, camera)
    write_tracker_model(locations, learned)
    print(f"make_tracker_model: wrote {len(locations.corners)} surface locations and the model "
          f"learnt from {sum(len(f.points) for f in frames)} rendered frames to {TRACKER_MODEL_FILE}")


if __name__ == "__main__":
    main()
