"""Drive from Webcam through bpy.ops and the take's step(), on real frames (no camera exists here).

The actor is skimage's astronaut (public domain) moved, scaled and turned in 640x480 frames, as
a video of known frame rate and as folders of images; the avatar is the bundled ICT library (a
few of its expressions as shape keys), stood up in Blender facing -Y. The take's step() is what
the modal timer calls in the UI; here execute() and the tests call it: a bad frame or a removed
avatar ends the take with one line and keeps what it recorded. Not covered headless: the
modal/timer path itself and the gpu viewport overlay (both need a window).
"""
import math
import re
import time

import bpy
import cv2
import numpy as np
import pytest
from skimage import data

from exclone_addon.blender import camera_preview, live_panel, mesh_io, webcam_take
from exclone_addon.core import capture
from exclone_addon.core.library import load_library
from blender_tests.helpers.animation import keyframes
from blender_tests.helpers.layout import RecordingLayout
from blender_tests.helpers.takes import astronaut_frame

KEYS = ["jawOpen", "eyeBlink_L", "eyeBlink_R", "mouthSmile_L", "mouthSmile_R", "browInnerUp_L",
        "browDown_R", "mouthFunnel", "mouthPucker", "cheekSquint_L"]
FACE_CENTRE = (224.0, 130.0)     # between the astronaut's eyes and mouth, in data.astronaut()
FRAME_SIZE = (640, 480)
VIDEO_FPS = 20                   # the session calibrates over the first second: 20 frames
FOLDER_FPS = capture.FOLDER_FRAME_RATE
FOLDER_FPS_INT = round(FOLDER_FPS)    # the session calibrates over the folder's first second
ROLL_DEGREES = 12.0              # the image turned counter-clockwise on screen
GREEN = np.array(camera_preview.LANDMARK_COLOUR) / 255.0


def actor_frame(dx=0.0, dy=0.0, scale=1.0, angle=0.0):
    """The astronaut's face at twice its size, moved by (dx, dy) pixels from the frame's centre,
    scaled and turned by `angle` degrees counter-clockwise on screen."""
    astronaut = cv2.cvtColor(data.astronaut(), cv2.COLOR_RGB2BGR)
    matrix = cv2.getRotationMatrix2D(FACE_CENTRE, angle, 2.0 * scale)
    matrix[:, 2] += (FRAME_SIZE[0] / 2 + dx - FACE_CENTRE[0], FRAME_SIZE[1] / 2 + dy - FACE_CENTRE[1])
    return cv2.warpAffine(astronaut, matrix, FRAME_SIZE, borderValue=(90, 90, 90))


def wobble(k):
    """A small, known head movement for frame k: translation and scale."""
    return dict(dx=25 * math.sin(k / 4), dy=12 * math.cos(k / 5), scale=1 + 0.1 * math.sin(k / 6))


def write_folder(folder, frames):
    folder.mkdir()
    for k, frame in enumerate(frames):
        cv2.imwrite(str(folder / f"frame_{k:03d}.png"), frame)
    return folder


@pytest.fixture(scope="module")
def ict():
    return load_library().subset(KEYS)


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    """44 frames at 20 fps of a moving, scaling face."""
    path = tmp_path_factory.mktemp("video") / "actor.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), VIDEO_FPS, FRAME_SIZE)
    for k in range(44):
        writer.write(actor_frame(**wobble(k)))
    writer.release()
    return path


@pytest.fixture(scope="module")
def turning_folder(tmp_path_factory):
    """A second (30 frames) upright for the calibration, then 14 frames turned by ROLL_DEGREES."""
    frames = [actor_frame(**wobble(k)) for k in range(30)]
    frames += [actor_frame(angle=ROLL_DEGREES) for _ in range(14)]
    return write_folder(tmp_path_factory.mktemp("turning") / "frames", frames)


@pytest.fixture(scope="module")
def gap_folder(tmp_path_factory):
    """30 calibration frames, 4 frames without a face (a grey wall), then the face again."""
    frames = [actor_frame(**wobble(k)) for k in range(30)]
    frames += [np.full((FRAME_SIZE[1], FRAME_SIZE[0], 3), 90, np.uint8)] * 4
    frames += [actor_frame(**wobble(k)) for k in range(40, 46)]
    return write_folder(tmp_path_factory.mktemp("gap") / "frames", frames)


@pytest.fixture(autouse=True)
def no_take_left():
    webcam_take.running = webcam_take.last_take = None
    yield
    webcam_take.running = webcam_take.last_take = None


def add_avatar(ict, name="avatar"):
    """The ICT head (+Y up, looking along +Z) with KEYS as shape keys, stood up facing -Y."""
    obj = mesh_io.object_from_mesh(name, ict.mesh)
    mesh_io.write_shape_keys(obj, ict.names, ict.deltas)
    obj.rotation_euler = (math.pi / 2, 0.0, 0.0)
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)
    return obj


def key_values(obj):
    return {block.name: block.value for block in obj.data.shape_keys.key_blocks[1:]}


def roll_degrees(rotation):
    """Rotation about -Y (a face looking along -Y turning counter-clockwise as seen from the
    front), in degrees, of a world rotation (mathutils Quaternion)."""
    matrix = np.array(rotation.to_matrix())
    return math.degrees(math.atan2(matrix[2, 0], matrix[0, 0]))


def reports(capfd, kind="Info"):
    return [line[len(kind) + 2:] for line in capfd.readouterr().out.splitlines()
            if line.startswith(kind + ": ")]


def green_pixels(image):
    pixels = np.array(image.pixels[:]).reshape(-1, 4)[:, :3]
    return int((np.abs(pixels - GREEN).max(axis=1) < 1e-3).sum())


# -- a recorded take ------------------------------------------------------------------------------

def test_video_take_keys_every_shape_key_at_the_videos_time(ict, video, capfd):
    obj = add_avatar(ict)
    bpy.context.scene.frame_current = 5
    assert bpy.ops.exclone.drive_from_webcam(source_type='VIDEO', filepath=str(video),
                                             record=True) == {'FINISHED'}
    message = reports(capfd)[-1]
    assert re.match(r"Take on 'avatar': 44 frames from video actor\.avi \(44 frames, 20 fps\), "
                    r"44 with a face, keyed at frames 28-57 \(the source ended", message), message
    # The first second calibrates the neutral face; from its last frame on every frame is keyed
    # at frame = 5 + round(t * 24 fps), t = k / 20 s.
    expected = [5 + round(k / VIDEO_FPS * 24) for k in range(VIDEO_FPS - 1, 44)]
    curves = keyframes(obj.data.shape_keys)
    assert set(curves) == {f'key_blocks["{name}"].value' for name in KEYS}
    values = []
    for points in curves.values():
        assert [frame for frame, _ in points] == sorted(set(expected))
        values += [value for _, value in points]
    assert 0.0 <= min(values) and max(values) <= 1.0
    assert max(values) > 0.0
    assert obj.animation_data is None          # no head target: the object is not animated
    assert obj.rotation_mode == 'XYZ'
    assert bpy.data.images[camera_preview.PREVIEW_IMAGE].size[:] == (camera_preview.PREVIEW_WIDTH, 240)


def test_reading_the_faces_image_is_the_takes_choice(ict, video):
    """With Read the Face's Image off the keys follow the points and eyes alone: the same take
    keys other values, each still in [0, 1]."""
    values = {}
    for use_appearance in (True, False):
        obj = add_avatar(ict, name=f"avatar_{use_appearance}")
        assert bpy.ops.exclone.drive_from_webcam(source_type='VIDEO', filepath=str(video),
                                                 record=True, use_appearance=use_appearance,
                                                 show_overlay=False) == {'FINISHED'}
        curves = keyframes(obj.data.shape_keys)
        values[use_appearance] = np.array([[value for _, value in curves[path]]
                                           for path in sorted(curves)])
    assert values[True].shape == values[False].shape
    assert 0.0 <= values[False].min() and values[False].max() <= 1.0
    assert np.abs(values[True] - values[False]).max() > 0.01


def test_a_take_on_the_worker_thread_keys_what_step_keys_and_its_ticks_stay_short(ict, video):
    """What the modal operator does: the worker thread reads and tracks, tick() on the main
    thread only applies; a file's every frame is applied in order, as step() applies them.
    The first second's calibration runs in the worker: no tick waits for it."""
    runs = {}
    for threaded in (False, True):
        obj = add_avatar(ict, f"avatar {threaded}")
        take = webcam_take.start_take(bpy.context, source_type='VIDEO', filepath=str(video),
                                      record=True)
        if threaded:
            take.start_worker()
            while take.tick():
                time.sleep(0.001)
        else:
            while take.step():
                pass
        take.close()
        runs[threaded] = (take, keyframes(obj.data.shape_keys))
    (plain, plain_keys), (threaded, threaded_keys) = runs[False], runs[True]
    assert threaded.end_reason == "the source ended" and not threaded.interrupted
    assert threaded.frames_read == plain.frames_read == 44
    assert threaded.worker.wait(5.0) and threaded.source._capture is None    # closed by the worker
    assert threaded_keys.keys() == plain_keys.keys()
    for path, points in plain_keys.items():
        np.testing.assert_allclose(threaded_keys[path], points, atol=1e-9)
    # a tick applies in about a millisecond; one may wait a few for the GIL while the worker
    # runs Python, none for the calibration (0.75-9 s when step() does it)
    assert np.median(threaded.apply_ms) <= 2.0, np.median(threaded.apply_ms)
    assert max(threaded.apply_ms) < 50.0, list(np.round(threaded.apply_ms, 1))
    assert len(threaded.latency_ms) == 44 - VIDEO_FPS + 1


def test_head_rotation_follows_the_turned_image(ict, turning_folder):
    obj = add_avatar(ict)
    rest = obj.rotation_euler.to_quaternion()
    assert bpy.ops.exclone.drive_from_webcam(source_type='FOLDER', filepath=str(turning_folder),
                                             record=True, head_target='OBJECT') == {'FINISHED'}
    assert obj.rotation_mode == 'QUATERNION'
    turned = obj.rotation_quaternion @ rest.inverted()    # the head's rotation in world axes
    roll = roll_degrees(turned)
    print(f"object roll {roll:.2f} degrees for an image turned by {ROLL_DEGREES}")
    assert abs(roll - ROLL_DEGREES) < 2.5
    assert turned.angle < math.radians(ROLL_DEGREES + 3)   # little pitch or yaw besides
    # keyed with the shape keys, at the same frames
    rotation = keyframes(obj)
    assert set(rotation) == {"rotation_quaternion"}
    shape_frames = [f for f, _ in next(iter(keyframes(obj.data.shape_keys).values()))]
    assert [f for f, _ in rotation["rotation_quaternion"]] == shape_frames


def test_head_rotation_onto_a_bone(ict, turning_folder):
    add_avatar(ict)
    armature_data = bpy.data.armatures.new("rig")
    armature = bpy.data.objects.new("rig", armature_data)
    bpy.context.scene.collection.objects.link(armature)
    armature.rotation_euler = (0.0, 0.0, 0.5)       # the armature itself is turned about Z
    bpy.context.view_layer.objects.active = armature
    bpy.ops.object.mode_set(mode='EDIT')
    bone = armature_data.edit_bones.new("head")
    bone.head, bone.tail, bone.roll = (0, 0, 1.5), (0, 0, 1.8), 0.7
    bpy.ops.object.mode_set(mode='OBJECT')
    bpy.context.view_layer.objects.active = bpy.data.objects["avatar"]
    assert bpy.ops.exclone.drive_from_webcam(
        source_type='FOLDER', filepath=str(turning_folder), record=True, head_target='BONE',
        armature="rig", bone="head") == {'FINISHED'}
    bpy.context.view_layer.update()
    pose_bone = armature.pose.bones["head"]
    posed = (armature.matrix_world @ pose_bone.matrix).to_quaternion()
    rest = (armature.matrix_world @ pose_bone.bone.matrix_local).to_quaternion()
    roll = roll_degrees(posed @ rest.inverted())
    print(f"bone roll {roll:.2f} degrees")
    assert abs(roll - ROLL_DEGREES) < 2.5
    assert 'pose.bones["head"].rotation_quaternion' in keyframes(armature)


def test_no_face_holds_the_pose_and_says_so_and_the_preview_shows_the_landmarks(ict, gap_folder):
    obj = add_avatar(ict)
    take = webcam_take.start_take(bpy.context, source_type='FOLDER', filepath=str(gap_folder),
                           record=True)
    image_pixels, statuses, values = [], [], []
    try:
        while take.step():
            statuses.append(take.status)
            values.append(key_values(obj))
            image = bpy.data.images[camera_preview.PREVIEW_IMAGE]
            image_pixels.append((np.array(image.pixels[:]), green_pixels(image)))
    finally:
        take.close()
    assert len(statuses) == 40 and take.end_reason == "the source ended"
    assert statuses[29] == "tracking"
    for k in range(30, 34):                         # the grey wall
        assert statuses[k] == "no face in view: holding the last pose"
        assert values[k] == values[29]
        assert image_pixels[k][1] == 0              # no landmarks drawn
    assert statuses[34:] == ["tracking"] * 6        # the face is found again
    assert values[-1] != values[29]
    # the held pose is keyed too, at the frames of the faceless images
    for points in keyframes(obj.data.shape_keys).values():
        held = dict(points)
        frames = [1 + round(k / FOLDER_FPS * 24) for k in range(29, 34)]
        assert len({held[f] for f in frames}) == 1
    # the preview: the frame with the landmarks in LANDMARK_COLOUR, changing with the frames
    for _, green in image_pixels[:30] + image_pixels[34:]:
        assert green > 300                          # 468 points, 2x2 dots, some overlapping
    assert not np.array_equal(image_pixels[0][0], image_pixels[1][0])
    assert take.frames_with_face == 36


def test_a_lost_camera_ends_the_take_and_keeps_what_was_recorded(ict, video):
    class UnpluggedCamera(capture.FrameSource):
        """The video's frames, then what a camera that stops delivering does: CameraLost."""
        is_live = True
        description = "camera 0"

        def __init__(self, frames):
            self.frames = iter(frames)

        def read(self):
            frame = next(self.frames, None)
            if frame is None:
                raise capture.CameraLost("camera 0 stopped delivering frames")
            return frame

    obj = add_avatar(ict)
    with capture.open_source(str(video)) as source:
        frames = list(source)[:26]
    take = webcam_take.start_take(bpy.context, source_type='VIDEO', filepath=str(video), record=True)
    take.close()
    take.source = UnpluggedCamera(frames)
    while take.step():
        pass
    assert take.interrupted and take.frames_read == 26
    kind, message = webcam_take.take_report(take)
    assert kind == {'WARNING'}
    assert message.startswith("camera 0 stopped delivering frames: the take ended; Take on "
                              "'avatar': 26 frames from camera 0, 26 with a face, keyed at "
                              "frames 1-"), message
    assert message.endswith("(what was recorded is kept)")
    # a camera's keys start at the take's first keyed frame: 7 frames keyed (19..25)
    for points in keyframes(obj.data.shape_keys).values():
        assert [f for f, _ in points] == [1 + round((k - 19) / VIDEO_FPS * 24) for k in range(19, 26)]


BAD_FRAME = 33          # after the folder's one second of calibration and 4 keyed frames


@pytest.mark.parametrize("case, problem", [
    ("unreadable", "image frame_033.png is unreadable"),
    ("1x1", "image frame_033.png is 1x1 pixels; a face needs at least 24x24"),
    ("another size", "image frame_033.png is 320x240 pixels but the take's first frame was "
                     "640x480: a take's frames must all be one size"),
])
def test_a_bad_frame_ends_the_take_in_one_line_and_keeps_the_keyframes_before_it(
        ict, tmp_path, capfd, case, problem):
    frames = [astronaut_frame(k) for k in range(BAD_FRAME + 3)]
    folder = write_folder(tmp_path / "frames", frames)
    bad = folder / f"frame_{BAD_FRAME:03d}.png"
    if case == "unreadable":
        bad.write_bytes(b"not a png")
    else:
        cv2.imwrite(str(bad), frames[BAD_FRAME][:1, :1] if case == "1x1"
                    else cv2.resize(frames[BAD_FRAME], (320, 240)))
    obj = add_avatar(ict)
    capfd.readouterr()
    assert bpy.ops.exclone.drive_from_webcam(source_type='FOLDER', filepath=str(folder),
                                             record=True, head_target='OBJECT') == {'FINISHED'}
    output = capfd.readouterr()
    assert "Traceback" not in output.out + output.err
    # keyed from the calibration's last frame (29) up to the bad frame, at 1 + round(t * 24)
    keyed = sorted({1 + round(k / FOLDER_FPS * 24) for k in range(FOLDER_FPS_INT - 1, BAD_FRAME)})
    warnings = [line for line in output.out.splitlines() if line.startswith("Warning: ")]
    assert warnings == [
        f"Warning: {problem}: the take ended; Take on 'avatar': {BAD_FRAME} frames from "
        f"{len(frames)} images in {folder}, {BAD_FRAME} with a face, keyed at frames "
        f"{keyed[0]}-{keyed[-1]} (what was recorded is kept)"]
    for points in keyframes(obj.data.shape_keys).values():
        assert [frame for frame, _ in points] == keyed
    assert [frame for frame, _ in keyframes(obj)["rotation_quaternion"]] == keyed
    assert webcam_take.running is None and webcam_take.last_take.frames_read == BAD_FRAME


def test_an_avatar_removed_during_the_take_ends_it_in_one_line(ict, video):
    obj = add_avatar(ict)
    take = webcam_take.start_take(bpy.context, source_type='VIDEO', filepath=str(video),
                                  record=True)
    try:
        for _ in range(VIDEO_FPS + 2):
            assert take.step()
        bpy.data.objects.remove(obj)
        assert not take.step()
    finally:
        take.close()
    kind, message = webcam_take.take_report(take)
    assert kind == {'WARNING'} and take.interrupted
    assert message.startswith("the avatar was removed during the take; Take on 'avatar': "
                              f"{VIDEO_FPS + 3} frames from video actor.avi"), message


# -- undo -----------------------------------------------------------------------------------------

def test_undo_after_a_take_restores_the_state_before_it(ict, turning_folder):
    """Background Blender pushes no undo step for an operator called from Python (the 'UNDO'
    option acts in the UI), so the steps are pushed by hand around the take."""
    obj = add_avatar(ict)
    before_rotation, before_values = tuple(obj.rotation_euler), key_values(obj)
    window = bpy.context.window_manager.windows[0]
    with bpy.context.temp_override(window=window):
        bpy.ops.ed.undo_push(message="before")
        bpy.ops.exclone.drive_from_webcam(source_type='FOLDER', filepath=str(turning_folder),
                                          record=True, head_target='OBJECT', max_frames=34)
        bpy.ops.ed.undo_push(message="after")
        assert keyframes(obj.data.shape_keys) and obj.rotation_mode == 'QUATERNION'
        bpy.ops.ed.undo()
    obj = bpy.data.objects["avatar"]
    assert obj.data.shape_keys.animation_data is None and obj.animation_data is None
    assert key_values(obj) == before_values
    assert obj.rotation_mode == 'XYZ' and tuple(obj.rotation_euler) == before_rotation
    assert camera_preview.PREVIEW_IMAGE not in bpy.data.images


# -- bad input ------------------------------------------------------------------------------------

@pytest.mark.parametrize("case", ["missing video", "folder without images", "camera 63",
                                  "folder as video", "missing bone"])
def test_bad_sources_report_and_change_nothing(ict, tmp_path, case):
    obj = add_avatar(ict)
    before = key_values(obj)
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("not an image")
    arguments, message = {
        "missing video": (dict(source_type='VIDEO', filepath=str(tmp_path / "none.mp4")),
                          "not found: .*none.mp4"),
        "folder without images": (dict(source_type='FOLDER', filepath=str(empty)),
                                  "folder .*empty holds no images"),
        "camera 63": (dict(source_type='CAMERA', camera_index=63), "no camera at index 63"),
        "folder as video": (dict(source_type='VIDEO', filepath=str(empty)),
                            "is a folder: choose Image Folder"),
        "missing bone": (dict(source_type='CAMERA', camera_index=63, head_target='BONE',
                              armature="rig", bone="head"),
                         "'rig' is not an armature in this file"),
    }[case]
    arguments.setdefault("head_target", 'OBJECT')
    with pytest.raises(RuntimeError, match=message):
        bpy.ops.exclone.drive_from_webcam(record=True, **arguments)
    assert obj.data.shape_keys.animation_data is None and obj.animation_data is None
    assert obj.rotation_mode == 'XYZ'
    assert key_values(obj) == before
    assert camera_preview.PREVIEW_IMAGE not in bpy.data.images and webcam_take.running is None


def test_an_avatar_without_shape_keys_or_face_is_refused_before_the_camera_opens(ict):
    bare = mesh_io.object_from_mesh("bare", ict.mesh)
    bpy.context.view_layer.objects.active = bare
    with pytest.raises(RuntimeError, match="'bare' has no shape keys besides the basis"):
        bpy.ops.exclone.drive_from_webcam(camera_index=63)
    bpy.ops.mesh.primitive_cube_add()
    cube = bpy.context.active_object
    cube.shape_key_add(name="Basis")
    cube.shape_key_add(name="up").data[0].co = (2, 2, 2)
    # the avatar's check comes first: camera 63 does not exist, but that is not what is said
    with pytest.raises(RuntimeError, match="'Cube': the tracker's face does not register onto "
                                           "this avatar"):
        bpy.ops.exclone.drive_from_webcam(camera_index=63)
    assert cube.data.shape_keys.animation_data is None
    assert camera_preview.PREVIEW_IMAGE not in bpy.data.images
    with pytest.raises(RuntimeError, match="no shape keys with ARKit names"):
        bpy.ops.exclone.drive_from_webcam(camera_index=63, key_set='ARKIT')


# -- the running take's operators -----------------------------------------------------------------

def test_calibrate_and_stop_act_on_the_running_take(ict, video):
    for name in ("calibrate_neutral", "stop_webcam"):
        with pytest.raises(RuntimeError, match="No take is running"):
            getattr(bpy.ops.exclone, name)()
    add_avatar(ict)
    take = webcam_take.start_take(bpy.context, source_type='VIDEO', filepath=str(video))
    webcam_take.running = take
    try:
        with pytest.raises(RuntimeError, match="A take is running"):
            bpy.ops.exclone.drive_from_webcam()
        for _ in range(VIDEO_FPS):
            assert take.step()
        assert take.status == "tracking" and take.session.calibrated
        assert bpy.ops.exclone.calibrate_neutral() == {'FINISHED'}
        assert take.step()
        assert take.status.startswith(f"calibrating 1/{VIDEO_FPS}")
        for _ in range(VIDEO_FPS - 1):
            assert take.step()
        assert take.status == "tracking"
        assert bpy.ops.exclone.stop_webcam() == {'FINISHED'}
        assert not take.step() and take.end_reason == "stopped"
    finally:
        take.close()


def test_calibrate_during_a_take_on_the_worker_thread_restarts_the_calibration(ict, video):
    add_avatar(ict)
    take = webcam_take.start_take(bpy.context, source_type='VIDEO', filepath=str(video))
    webcam_take.running = take
    take.start_worker()
    statuses = []
    try:
        while take.tick() and not take.session.calibrated:
            time.sleep(0.001)
        assert bpy.ops.exclone.calibrate_neutral() == {'FINISHED'}
        assert take.status == "calibrating: hold a neutral face"
        applied = take.frames_read
        while take.tick():
            if take.frames_read != applied:
                applied = take.frames_read
                statuses.append(take.status)
            time.sleep(0.001)
    finally:
        take.close()
    # the worker took the request up at its next frame: a new calibration from its first frame
    assert f"calibrating 1/{VIDEO_FPS}: hold a neutral face" in statuses, statuses
    assert take.end_reason == "the source ended" and take.frames_read == 44


def test_refine_take_rewrites_the_takes_keyframes_as_one_undo_step(ict, video, capfd):
    with pytest.raises(RuntimeError, match="Record a take first"):
        bpy.ops.exclone.refine_take()
    obj = add_avatar(ict)
    window = bpy.context.window_manager.windows[0]
    with bpy.context.temp_override(window=window):
        bpy.ops.exclone.drive_from_webcam(source_type='VIDEO', filepath=str(video), record=True)
        recorded = keyframes(obj.data.shape_keys)
        bpy.ops.ed.undo_push(message="take")
        assert bpy.ops.exclone.refine_take() == {'FINISHED'}
        message = reports(capfd)[-1]
        assert re.fullmatch(r"Refined 25 frames of the take on 'avatar', mean change [\d.]+",
                            message), message
        refined = keyframes(obj.data.shape_keys)
        assert set(refined) == set(recorded)
        change = 0.0
        for path, points in refined.items():
            assert [f for f, _ in points] == [f for f, _ in recorded[path]]
            assert all(0.0 <= value <= 1.0 for _, value in points)
            change = max(change, max(abs(a[1] - b[1]) for a, b in zip(points, recorded[path])))
        assert change > 1e-3
        bpy.ops.ed.undo_push(message="refined")
        bpy.ops.ed.undo()
    restored = keyframes(bpy.data.objects["avatar"].data.shape_keys)
    for path, points in restored.items():
        assert np.allclose(points, recorded[path], atol=1e-6)


# -- chessboard calibration -----------------------------------------------------------------------

KNOWN_CAMERA = dict(fx=610.0, fy=610.0, cx=331.0, cy=232.0)


def chessboard_views(count):
    """A 10x7-square chessboard (9x6 inner corners) seen by KNOWN_CAMERA from `count` poses."""
    square, margin = 30, 30
    board = np.full((7 * square + 2 * margin, 10 * square + 2 * margin), 255, np.uint8)
    for row in range(7):
        for column in range(10):
            if (row + column) % 2 == 0:
                y, x = margin + row * square, margin + column * square
                board[y:y + square, x:x + square] = 0
    k = np.array([[KNOWN_CAMERA["fx"], 0, KNOWN_CAMERA["cx"]],
                  [0, KNOWN_CAMERA["fy"], KNOWN_CAMERA["cy"]], [0, 0, 1]])
    centred = np.array([[1, 0, -board.shape[1] / 2], [0, 1, -board.shape[0] / 2], [0, 0, 1]])
    views = []
    for i in range(count):
        rotation, _ = cv2.Rodrigues(np.radians([25 * math.sin(1.3 * i + 0.4),
                                                25 * math.cos(0.9 * i), 8 * math.sin(i)]))
        translation = np.array([30 * math.sin(i), 20 * math.cos(2 * i), 800 + 60 * (i % 3)])
        homography = k @ np.column_stack((rotation[:, 0], rotation[:, 1], translation)) @ centred
        views.append(cv2.cvtColor(cv2.warpPerspective(board, homography, FRAME_SIZE,
                                                      borderValue=128), cv2.COLOR_GRAY2BGR))
    return views


def test_calibrate_camera_from_chessboards_is_used_by_later_takes(ict, tmp_path, video, capfd):
    webcam = bpy.context.scene.exclone.webcam
    too_few = write_folder(tmp_path / "faces", [actor_frame(), actor_frame(angle=5)])
    with pytest.raises(RuntimeError, match=r"a 9x6 chessboard was found in 0 of the images; at "
                                           r"least \d+ views are needed"):
        bpy.ops.exclone.calibrate_camera(directory=str(too_few))
    with pytest.raises(RuntimeError, match="no camera at index 63"):
        bpy.ops.exclone.calibrate_camera(camera_frames=5, camera_index=63)
    assert not webcam.calibrated and webcam.fx == 0.0

    boards = write_folder(tmp_path / "boards", chessboard_views(10))
    assert bpy.ops.exclone.calibrate_camera(directory=str(boards)) == {'FINISHED'}
    print(reports(capfd)[-1])
    assert webcam.calibrated
    assert (webcam.calibration_width, webcam.calibration_height) == FRAME_SIZE
    assert webcam.fx == pytest.approx(KNOWN_CAMERA["fx"], rel=0.02)
    assert webcam.fy == pytest.approx(KNOWN_CAMERA["fy"], rel=0.02)
    assert webcam.cx == pytest.approx(KNOWN_CAMERA["cx"], abs=8)
    assert webcam.cy == pytest.approx(KNOWN_CAMERA["cy"], abs=8)
    assert webcam.calibration_rms < 0.5

    add_avatar(ict)
    take = webcam_take.start_take(bpy.context, source_type='VIDEO', filepath=str(video))
    take.close()
    assert take.session.camera.fx == pytest.approx(webcam.fx)
    assert take.session.camera.cy == pytest.approx(webcam.cy)
    # at another size the intrinsics scale with the image
    half = webcam_take.calibrated_camera(webcam, (320, 240))
    assert half.fx == pytest.approx(webcam.fx / 2) and half.cx == pytest.approx(
        (webcam.cx + 0.5) / 2 - 0.5)
    take = webcam_take.start_take(bpy.context, source_type='VIDEO', filepath=str(video),
                           use_calibration=False)
    take.close()
    assert take.session.camera is None    # the default from the first frame's size


# -- the panel ------------------------------------------------------------------------------------

class PanelLayout(RecordingLayout):
    def _sub(self, *args, **kwargs):
        return PanelLayout(self.log)

    row = column = box = split = _sub

    def prop_search(self, data, name, search_data, search_name, **kwargs):
        assert name in data.bl_rna.properties and search_name in search_data.bl_rna.properties
        self.log.append(("prop_search", name))


def draw_panel():
    log = []
    live_panel.draw(PanelLayout(log), bpy.context)
    return log


def test_panel_section_offers_the_choices_and_the_status(ict):
    assert bpy.types.EXCLONE_PT_webcam.bl_parent_id == "EXCLONE_PT_main"
    log = draw_panel()
    operators = [entry[1] for entry in log if entry[0] == "operator"]
    assert operators == ["exclone.drive_from_webcam", "exclone.calibrate_neutral",
                         "exclone.refine_take", "exclone.import_take_csv",
                         "exclone.export_take_csv", "exclone.calibrate_camera"]
    assert ("prop", "camera_index") in log and ("label", "Not running") in log
    assert ("prop", "use_appearance") in log
    assert ("label", "Preferences' webcam: 0") in log

    webcam = bpy.context.scene.exclone.webcam
    webcam.source_type, webcam.head_target = 'VIDEO', 'BONE'
    webcam.head_armature = bpy.data.objects.new("rig", bpy.data.armatures.new("rig"))
    log = draw_panel()
    assert ("prop", "video_path") in log and ("prop", "camera_index") not in log
    assert ("prop_search", "head_bone") in log

    add_avatar(ict)
    webcam_take.running = type("RunningTake", (), {"status": "no face in view: holding the last pose"})
    log = draw_panel()
    assert "exclone.stop_webcam" in [entry[1] for entry in log if entry[0] == "operator"]
    assert ("label", "no face in view: holding the last pose") in log


def test_the_takes_operators_undo_as_they_should():
    # these change data: one undo step each; Stop and Calibrate change none, and an undo step
    # of theirs would split the running take's own
    for name in ("drive_from_webcam", "refine_take", "calibrate_camera"):
        assert {'REGISTER', 'UNDO'} <= getattr(bpy.ops.exclone, name).bl_options, name
    for name in ("stop_webcam", "calibrate_neutral"):
        assert 'UNDO' not in getattr(bpy.ops.exclone, name).bl_options, name
