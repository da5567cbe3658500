"""scripts/track_video.py: the offline tracker's command line and JSON contract; bad input and
a bad frame end with one line (the frames tracked before a bad frame are kept)."""
import functools
import importlib.util
import json
import subprocess
import sys

import bpy
import cv2
import numpy as np
import pytest

from blender_tests.helpers.paths import REPO_ROOT
from exclone_addon.blender import mesh_io
from exclone_addon.core.face_models import IBUG68_FROM_MEDIAPIPE
from exclone_addon.core.library import load_library
from blender_tests.helpers.takes import astronaut, astronaut_frame

SCRIPT = REPO_ROOT / "scripts" / "track_video.py"
AVATAR_SHAPES = ("jawOpen", "eyeBlink_L", "mouthSmile_L", "browInnerUp_L")


@functools.lru_cache(maxsize=1)
def track_video():
    spec = importlib.util.spec_from_file_location("track_video", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def run_cli(*args):
    """The script in its own process: (exit code, stdout, stderr)."""
    done = subprocess.run([sys.executable, str(SCRIPT), *map(str, args)], capture_output=True,
                          text=True, timeout=120)
    return done.returncode, done.stdout, done.stderr


def write_frames(folder, count, blank=()):
    folder.mkdir()
    for k in range(count):
        image = np.full((480, 640, 3), 90, np.uint8) if k in blank else astronaut_frame(k)
        cv2.imwrite(str(folder / f"frame_{k:03d}.png"), image)
    return folder


def test_folder_of_frames_to_json(tmp_path):
    frames = write_frames(tmp_path / "frames", 12, blank=(6,))
    out = tmp_path / "take.json"
    assert track_video().main([str(frames), "--out", str(out), "--calibration-frames", "4",
                               "--camera-fx", "700"]) == 0
    result = json.loads(out.read_text())
    assert result["format"] == "exclone-track" and result["format_version"] == 1
    assert result["source"]["frame_size"] == [640, 480]
    assert result["source"]["description"] == f"12 images in {frames}"
    assert result["camera"] == {"fx": 700.0, "fy": 700.0, "cx": 320.0, "cy": 240.0, "given": ["fx"]}
    assert set(result["models"]) >= {"detector", "landmarks", "tracker_model"}
    assert result["avatar"] is None
    records = result["frames"]
    assert [r["index"] for r in records] == list(range(12))
    np.testing.assert_allclose([r["timestamp"] for r in records], np.arange(12) / 30.0, atol=1e-6)
    assert [r["found"] for r in records] == [k != 6 for k in range(12)]
    assert result["summary"]["frames"] == 12 and result["summary"]["frames_with_face"] == 11
    for record in records:
        assert len(record["head_pose"]["quaternion_xyzw"]) == 4
        assert {"detect", "landmarks", "fit", "weights", "total"} <= set(record["stage_ms"])
        if record["found"]:
            landmarks = np.array(record["landmarks"])
            assert landmarks.shape == (468, 3)
            np.testing.assert_allclose(record["ibug68"], landmarks[IBUG68_FROM_MEDIAPIPE, :2])
    blank = records[6]
    assert "landmarks" not in blank and blank["status"].startswith("no face in view")
    assert blank["head_pose"] == records[5]["head_pose"]          # the last pose, held
    assert records[3]["head_rotation_blender_xyzw"] and "head_rotation_blender_xyzw" not in records[2]


def test_still_images_match_the_photograph(tmp_path):
    """--still-images on photographs of different sizes: each on its own; the 68 points of the
    astronaut land where the face models put them in the photograph itself."""
    frames = tmp_path / "photos"
    frames.mkdir()
    cv2.imwrite(str(frames / "a.png"), astronaut())
    cv2.imwrite(str(frames / "b.png"), astronaut_frame(0))
    out = tmp_path / "photos.json"
    assert track_video().main([str(frames), "--still-images", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["source"]["frame_sizes_vary"] and result["camera"]["per_frame"]
    first, second = result["frames"]
    assert first["camera"]["cx"] == 256.0 and second["camera"]["cx"] == 320.0
    # the first photograph is the unmoved astronaut: hand-measured outer eye corners (test_face_models)
    ibug = np.array(first["ibug68"])
    assert np.hypot(*(ibug[36] - (192.5, 100.5))) < 4 and np.hypot(*(ibug[45] - (258.0, 103.5))) < 4


def test_avatar_weights_by_shape_key_name(tmp_path):
    """A .blend avatar (ICT with four shape keys): weights per frame, by name, in 0..1."""
    library = load_library()
    mesh = bpy.data.meshes.new("Face")
    mesh.from_pydata(library.mesh.vertices.tolist(), [], [f.tolist() for f in library.mesh.faces()])
    obj = bpy.data.objects.new("Face", mesh)
    bpy.context.scene.collection.objects.link(obj)
    ids = [library.names.index(n) for n in AVATAR_SHAPES]
    mesh_io.write_shape_keys(obj, list(AVATAR_SHAPES), library.deltas[ids])
    blend = tmp_path / "avatar.blend"
    bpy.data.libraries.write(str(blend), {obj})
    bpy.data.objects.remove(obj)            # so that the file's "Face" is not renamed on loading
    bpy.data.meshes.remove(mesh)
    stamp = blend.stat().st_mtime_ns
    frames = write_frames(tmp_path / "frames", 6)
    out = tmp_path / "avatar.json"
    assert track_video().main([str(frames), "--avatar", f"{blend}:Face", "--out", str(out),
                               "--calibration-frames", "3"]) == 0
    result = json.loads(out.read_text())
    assert result["avatar"]["shape_keys"] == list(AVATAR_SHAPES)
    records = result["frames"]
    assert all("weights" not in r for r in records[:2])
    for record in records[2:]:
        assert list(record["weights"]) == list(AVATAR_SHAPES)
        assert all(0.0 <= w <= 1.0 for w in record["weights"].values())
    assert blend.stat().st_mtime_ns == stamp           # the avatar's file is only read


@pytest.mark.parametrize("args, message", [
    (["{tmp}/missing.mp4"], "not found: {tmp}/missing.mp4"),
    (["63"], "no camera at index 63"),
    (["{tmp}/junk.mp4"], "{tmp}/junk.mp4 is not a readable video"),
    (["{tmp}"], "folder {tmp} holds no images"),
    (["{tmp}/junk.mp4", "--out", "{tmp}/x.txt"], "--out must name a .json file"),
    (["{tmp}/junk.mp4", "--out", "{tmp}/junk.mp4"], "--out must name a .json file"),   # the input
    (["{tmp}/junk.mp4", "--frames", "0"], "argument --frames: must be at least 1"),
    (["{tmp}/junk.mp4", "--frames", "2.5"], "argument --frames: must be a whole number, got '2.5'"),
    (["{tmp}/junk.mp4", "--camera-fx", "-5"], "argument --camera-fx: must be positive"),
    (["{tmp}/junk.mp4", "--camera-fx", "nan"], "argument --camera-fx: must be a finite number"),
    (["{tmp}/junk.mp4", "--camera-cx", "inf"], "argument --camera-cx: must be a finite number"),
    (["{tmp}/junk.mp4", "--fps", "inf"], "argument --fps: must be a finite number, got 'inf'"),
    (["{tmp}/junk.mp4", "--fps", "nan"], "argument --fps: must be a finite number, got 'nan'"),
    (["{tmp}/junk.mp4", "--fps", "0"], "argument --fps: must be positive, got 0"),
    (["{tmp}/junk.mp4", "--calibration-frames", "inf"],
     "argument --calibration-frames: must be a whole number, got 'inf'"),
    (["{tmp}/junk.mp4", "--out", "{tmp}/junk.mp4/take.json"],
     "cannot write {tmp}/junk.mp4/take.json: {tmp}/junk.mp4 is a file, not a folder"),
    (["{tmp}/junk.mp4", "--bogus"], "unrecognized arguments: --bogus"),
    (["{tmp}/junk.mp4", "--avatar", "{tmp}/none.blend"], "--avatar not found"),
])
def test_bad_input_is_one_line_and_nonzero(tmp_path, capfd, args, message):
    (tmp_path / "junk.mp4").write_bytes(b"not a video" * 20)
    argv = [a.format(tmp=tmp_path) for a in args]
    assert track_video().main(argv) == 1
    captured = capfd.readouterr()
    lines = captured.err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("track_video: error: "), captured.err
    assert message.format(tmp=tmp_path) in lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["junk.mp4"]     # nothing written


def test_cli_process_exit_codes(tmp_path):
    code, _, err = run_cli(tmp_path / "missing.mp4")
    assert code == 1 and err.splitlines() == [f"track_video: error: not found: {tmp_path}/missing.mp4"]
    code, _, err = run_cli(63)
    assert code == 1 and err.splitlines() == ["track_video: error: no camera at index 63"]
    frames = write_frames(tmp_path / "frames", 2)
    code, out, err = run_cli(frames, "--out", tmp_path / "two.json")
    assert code == 0 and err == "" and "2 frames (2 with a face)" in out
    assert len(json.loads((tmp_path / "two.json").read_text())["frames"]) == 2


def strict_json(path):
    """The file's JSON; fails on NaN or Infinity (not JSON, though Python writes and reads them)."""
    def refuse(constant):
        raise AssertionError(f"{path} holds {constant}")
    return json.loads(path.read_text(), parse_constant=refuse)


@pytest.mark.parametrize("bad", ["unreadable", "1x1", "smaller"])
def test_a_bad_later_frame_ends_the_take_and_keeps_the_frames_before_it(tmp_path, capfd, bad):
    frames = write_frames(tmp_path / "frames", 6)
    if bad == "unreadable":
        (frames / "frame_004.png").write_bytes(b"not a png" * 10)
        expected = "frame 4: image "
    else:
        size = (1, 1) if bad == "1x1" else (320, 240)
        cv2.imwrite(str(frames / "frame_004.png"), cv2.resize(astronaut_frame(4), size))
        expected = f"frame 4: it is {size[0]}x{size[1]} pixels, the first was 640x480"
    out = tmp_path / "take.json"
    assert track_video().main([str(frames), "--out", str(out), "--calibration-frames", "2"]) == 1
    lines = capfd.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"track_video: error: {expected}"), lines
    assert lines[0].endswith(f"; the 4 frames before it are in {out}"), lines[0]
    result = strict_json(out)
    assert [r["index"] for r in result["frames"]] == [0, 1, 2, 3]
    assert all(r["found"] for r in result["frames"])
    assert result["summary"]["frames"] == 4 and result["summary"]["error"].startswith(expected)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames", "take.json"]   # no temporary


def test_a_one_pixel_still_image_ends_cleanly(tmp_path, capfd):
    """Among photographs, a 1x1 image: either the take stops there (one line, the photograph
    before it kept) or it is a frame without a face with its status; never a traceback."""
    photos = tmp_path / "photos"
    photos.mkdir()
    cv2.imwrite(str(photos / "a.png"), astronaut())
    cv2.imwrite(str(photos / "b.png"), np.zeros((1, 1, 3), np.uint8))
    cv2.imwrite(str(photos / "c.png"), astronaut_frame(0))
    out = tmp_path / "photos.json"
    code = track_video().main([str(photos), "--still-images", "--out", str(out)])
    err = capfd.readouterr().err
    result = strict_json(out)
    if code == 1:
        lines = err.splitlines()
        assert len(lines) == 1 and lines[0].startswith("track_video: error: frame 1: "), err
        assert [r["index"] for r in result["frames"]] == [0] and result["frames"][0]["found"]
        assert result["summary"]["error"].startswith("frame 1: ")
    else:
        assert code == 0 and err == ""
        assert [r["found"] for r in result["frames"]] == [True, False, True]
        assert result["frames"][1]["status"] and result["summary"]["error"] is None
