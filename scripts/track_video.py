"""Track a face offline: a video file, a camera or a folder of images -> one JSON file.

    python scripts/track_video.py INPUT [--avatar FILE.blend[:Object]] [--out OUT.json]
        [--camera-fx F] [--camera-fy F] [--camera-cx X] [--camera-cy Y] [--frames N]
        [--fps R] [--calibration-frames N] [--still-images]

INPUT: a video file, a camera index (0, 1, ...) or a folder of images (sorted by name). Per frame
the JSON holds the 468 FaceMesh landmarks, the 68-point subset in iBUG 300-W order (image pixels,
OpenCV convention: the centre of pixel (i, j) is (i, j)), the head pose (model -> camera rotation
as a quaternion x, y, z, w and a translation in the model's cm, OpenCV camera axes), the
shape-key weights by name when an avatar is given, and the time spent per stage; a header
describes the source, frame size, camera intrinsics and model versions.

--still-images: every frame is an unrelated photograph (e.g. an annotated test set): detection
on each, no temporal filtering, intrinsics from each image's size unless given.
--avatar needs Blender's bpy module (.venv/bin/python has it): the avatar's shape keys are read
from the .blend (or .fbx/.glb, or a folder with neutral.obj + one OBJ per shape), nothing is
written to it. Numbers must be finite (--fps, --camera-fx and --camera-fy also positive).
Exit code 0 on success; otherwise 1 and one line on stderr. A frame that cannot be tracked
(unreadable, of another size without --still-images, refused by the tracker) ends the take: the
frames before it are written, the summary's "error" says which frame and why (null after a
complete take), and the exit code is 1.
"""
import hashlib
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(REPO), str(REPO / "scripts")]  # exclone_addon, exclone_cli
from exclone_cli import Outputs, Parser, check_output_writable, number, run_main  # noqa: E402
from exclone_addon.core import capture, data, face_models, retarget, tracker_model  # noqa: E402
from exclone_addon.core.session import FaceTrackingSession  # noqa: E402
from exclone_addon.core.errors import ExCloneError  # noqa: E402
from exclone_addon.core.tracking import Camera  # noqa: E402

FORMAT = "exclone-track"
FORMAT_VERSION = 1
DEFAULT_CAMERA_FRAMES = 300
PROG = "track_video"


def parse_args(argv):
    parser = Parser(prog="track_video.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("input", help="video file, camera index or folder of images")
    parser.add_argument("--avatar", metavar="FILE.blend[:Object]",
                        help="mesh with shape keys whose weights are solved per frame (needs bpy)")
    parser.add_argument("--out", metavar="OUT.json",
                        help="output (default: out/<input name>_track.json)")
    for axis in ("fx", "fy", "cx", "cy"):
        parser.add_argument(f"--camera-{axis}", type=number(positive=axis in ("fx", "fy")),
                            metavar="PX",
                            help="camera intrinsics in pixels (default: f = max(width, height), "
                                 "the image centre)")
    parser.add_argument("--frames", type=number(int, at_least=1), metavar="N",
                        help=f"stop after N frames (a camera: default {DEFAULT_CAMERA_FRAMES})")
    parser.add_argument("--fps", type=number(positive=True), metavar="R",
                        help="frame rate given to a folder's images (default 30)")
    parser.add_argument("--calibration-frames", type=number(int, at_least=1), default=30,
                        metavar="N",
                        help="frames with a face that calibrate the actor's neutral (default 30)")
    parser.add_argument("--still-images", action="store_true",
                        help="treat every frame as an unrelated photograph")
    parser.add_argument("--no-appearance", action="store_true",
                        help="read expressions from the face's points and eyes alone, not from "
                             "its image too")
    return parser.parse_args(argv)


def output_path(args):
    """The JSON's path; ExCloneError at once if it cannot be written."""
    if args.out:
        out = Path(args.out)
    else:
        name = f"camera{args.input.strip()}" if args.input.strip().isdigit() else Path(args.input).stem
        out = Path("out") / f"{name}_track.json"
    if out.suffix.lower() != ".json":
        raise ExCloneError(f"--out must name a .json file, got {out}")
    check_output_writable(out)
    return out


def load_avatar(spec):
    """(AvatarRig, description) of a mesh with shape keys, read with Blender (bpy)."""
    try:
        from exclone_addon.blender import files
    except ImportError:
        raise ExCloneError("--avatar needs Blender's bpy module: run with .venv/bin/python or "
                           "blender -b --python") from None
    source = files.load_source(spec, role="--avatar")
    rig = retarget.AvatarRig.from_arrays(source.mesh.vertices, source.mesh.triangles(), source.deltas,
                                     source.names)
    return rig, source.description


def _file_digest(path):
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]


def model_versions():
    import cv2
    import tomllib
    models = data.MODELS_DIR
    manifest = tomllib.loads((REPO / "blender_manifest.toml").read_text())
    return {
        "exclone": manifest["version"],
        "detector": {"file": face_models.DETECTOR_MODEL, "from": "mediapipe 0.10.21",
                     "sha256_16": _file_digest(models / face_models.DETECTOR_MODEL)},
        "landmarks": {"file": face_models.LANDMARK_MODEL, "from": "mediapipe 0.10.21",
                      "sha256_16": _file_digest(models / face_models.LANDMARK_MODEL)},
        "tracker_model": {"file": data.TRACKER_MODEL_FILE.name, "format": tracker_model.TRACKER_MODEL_VERSION,
                          "sha256_16": _file_digest(data.TRACKER_MODEL_FILE)},
        "opencv": cv2.__version__, "numpy": np.__version__,
    }


def _rounded(array, decimals):
    return np.round(np.asarray(array, dtype=np.float64), decimals).tolist()


def frame_record(frame, result):
    record = {"index": frame.index, "timestamp": round(frame.timestamp, 6), "found": result.found,
              "status": result.status}
    if result.found:
        record["landmarks"] = _rounded(result.landmarks, 3)
        record["ibug68"] = _rounded(result.ibug68, 3)
    if result.rotation is not None:
        record["head_pose"] = {"quaternion_xyzw": _rounded(result.rotation.as_quat(), 7),
                               "translation": _rounded(result.translation, 5)}
    if result.head_rotation is not None:
        record["head_rotation_blender_xyzw"] = _rounded(result.head_rotation.as_quat(), 7)
    if result.weights is not None:
        record["weights"] = {name: round(value, 5) for name, value in result.weights.items()}
    record["stage_ms"] = {name: round(ms, 3) for name, ms in result.stage_ms.items()}
    return record


def _session(args, source, avatar):
    """(camera or None, FaceTrackingSession): the given intrinsics, else the first frame's
    (None for still images without given intrinsics: each frame's own)."""
    given = {axis: getattr(args, f"camera_{axis}") for axis in ("fx", "fy", "cx", "cy")}
    camera = None
    if any(v is not None for v in given.values()) or not args.still_images:
        camera = Camera.from_image_size(*source.frame_size, **given)
    return camera, FaceTrackingSession(avatar=avatar, camera=camera,
                                       calibration_frames=args.calibration_frames,
                                       still_images=args.still_images,
                                       appearance=not args.no_appearance)


def _tracked_frame(args, source, session, camera):
    """(the next frame's record, its width and height), or None at the end of the input.
    ExCloneError for a frame that cannot be tracked (unreadable, of another size, refused by
    the tracker)."""
    frame = source.read()
    if frame is None:
        return None
    width, height = source.frame_size
    if not args.still_images and (frame.image.shape[1], frame.image.shape[0]) != (width, height):
        raise ExCloneError(f"it is {frame.image.shape[1]}x{frame.image.shape[0]} pixels, the "
                           f"first was {width}x{height}; give --still-images for images of "
                           "different sizes")
    step_start = time.perf_counter()
    result = session.step(frame.image, frame.timestamp)
    record = frame_record(frame, result)
    record["stage_ms"]["total"] = round(1000 * (time.perf_counter() - step_start), 3)
    if camera is None:
        record["camera"] = _camera_dict(session.camera)
    return record, (frame.image.shape[1], frame.image.shape[0])


@dataclass
class Take:
    camera: object        # core.tracking.Camera, or None: each still image's own
    records: list         # one dict per frame tracked
    sizes: set            # the frames' (width, height)
    seconds: float
    error: str = None     # why the take stopped before the input's end, else None


def track(args, source, avatar):
    """Every frame up to --frames as a Take; a frame that cannot be tracked stops it there (the
    frames before it are kept) and is named in its error."""
    camera, session = _session(args, source, avatar)
    limit = args.frames or (DEFAULT_CAMERA_FRAMES if source.is_live else None)
    take = Take(camera, [], set(), 0.0)
    start = time.perf_counter()
    while limit is None or len(take.records) < limit:
        try:
            tracked = _tracked_frame(args, source, session, camera)
        except ExCloneError as exc:
            take.error = f"frame {len(take.records)}: {exc}"
            break
        if tracked is None:
            break
        take.records.append(tracked[0])
        take.sizes.add(tracked[1])
    take.seconds = time.perf_counter() - start
    return take


def _header(args, source, camera, avatar, avatar_description):
    given = sorted(axis for axis in ("fx", "fy", "cx", "cy")
                   if getattr(args, f"camera_{axis}") is not None)
    width, height = source.frame_size
    return {
        "format": FORMAT, "format_version": FORMAT_VERSION,
        "source": {"input": args.input, "description": source.description,
                   "is_live": source.is_live, "frame_rate": source.frame_rate,
                   "frame_size": [width, height]},
        # still images without given intrinsics: each frame's own, in its record
        "camera": dict(_camera_dict(camera) if camera else {"per_frame": True}, given=given),
        "conventions": {
            "pixels": "OpenCV: the centre of pixel (column i, row j) is (i, j)",
            "landmarks": "468 MediaPipe FaceMesh points: x, y image pixels, z FaceMesh depth "
                         "(pixels, smaller towards the camera)",
            "ibug68": "iBUG 300-W 68-point order (0-based), image pixels",
            "head_pose": "model (canonical face, cm, +Y up, looking along +Z) -> camera "
                         "(x right, y down, z forward); quaternion x, y, z, w",
            "head_rotation_blender": "relative to the calibrated neutral, Blender axes "
                                     "(+Z up, -Y forward)",
        },
        "models": model_versions(),
        "avatar": ({"input": args.avatar, "description": avatar_description,
                    "shape_keys": avatar.names} if avatar else None),
        "still_images": args.still_images,
        "calibration_frames": args.calibration_frames,
    }


def _summary(take):
    records = take.records
    found = [r for r in records if r["found"]]
    stages = sorted({k for r in records for k in r["stage_ms"]})
    return {
        "frames": len(records), "frames_with_face": len(found),
        "seconds": round(take.seconds, 3),
        "median_ms": {k: round(float(np.median([r["stage_ms"].get(k, 0.0) for r in records])), 3)
                      for k in stages} if records else {},
        # why the take stopped before the input's end (the frames before it are all here)
        "error": take.error,
    }


def run(args):
    """Track the input and write the JSON; returns it. A frame that cannot be tracked ends the
    take: the frames before it are written, then ExCloneError says which frame and why."""
    out = output_path(args)
    avatar, avatar_description = load_avatar(args.avatar) if args.avatar else (None, None)
    with capture.open_source(args.input, frame_rate=args.fps) as source:
        take = track(args, source, avatar)
        header = _header(args, source, take.camera, avatar, avatar_description)
    if take.error is not None and not take.records:
        raise ExCloneError(take.error)
    header["source"]["frame_sizes_vary"] = len(take.sizes) > 1
    header["summary"] = _summary(take)
    header["frames"] = take.records
    with Outputs() as outputs:
        text = json.dumps(header, separators=(",", ":"), allow_nan=False) + "\n"
        outputs.write(out, lambda path: path.write_text(text, encoding="utf-8"))
        outputs.commit()
    found = header["summary"]["frames_with_face"]
    if take.error is not None:
        raise ExCloneError(f"{take.error}; the {len(take.records)} frames before it are in {out}")
    print(f"track_video: {len(take.records)} frames ({found} with a face) from "
          f"{header['source']['description']} -> {out}")
    return header


def _camera_dict(camera):
    return {"fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy}


def main(argv):
    return run_main(PROG, lambda: run(parse_args(argv)))


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
