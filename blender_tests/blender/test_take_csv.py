"""Import Take CSV and Export Take CSV (blender.take_csv) through bpy.ops on a small avatar: a cube
with the ARKit-named keys jawOpen, eyeBlink_L and the halves browInnerUp_L/_R, and a key "smile"
without an ARKit name.

- import: keyframes at the playhead + round(t * scene fps) with the CSV's values (resampled when
  the rates differ), the head rotation onto the object, the report's counts and unmatched columns;
- export: the CSV equals the imported one in those columns; export -> import round-trips;
- bad input: one line, nothing changed; the poll messages; one undo step; the panel's buttons.
"""
import math

import bpy
import numpy as np
import pytest
from mathutils import Vector

from exclone_addon.blender import live_panel, webcam_take
from exclone_addon.core.library import ARKIT_BLENDSHAPES
from exclone_addon.core.livelink_csv import HEADER, LiveLinkTake, read_take_csv, write_take_csv
from blender_tests.helpers.animation import keyframes
from blender_tests.helpers.layout import RecordingLayout

ARKIT_KEYS = ["jawOpen", "eyeBlink_L", "browInnerUp_L", "browInnerUp_R"]
COLUMNS = {"JawOpen": "jawOpen", "EyeBlinkLeft": "eyeBlink_L", "BrowInnerUp": "browInnerUp"}


@pytest.fixture(autouse=True)
def no_take_left():
    webcam_take.running = webcam_take.last_take = None
    yield
    webcam_take.running = webcam_take.last_take = None


def add_avatar(name="face", keys=ARKIT_KEYS + ["smile"]):
    bpy.ops.mesh.primitive_cube_add()
    obj = bpy.context.active_object
    obj.name = name
    obj.shape_key_add(name="Basis")
    for i, key in enumerate(keys):
        obj.shape_key_add(name=key).data[i].co.z += 1.0
    return obj


def set_fps(fps):
    bpy.context.scene.render.fps, bpy.context.scene.render.fps_base = fps, 1.0


def key_curve(obj, name):
    return keyframes(obj.data.shape_keys).get(f'key_blocks["{name}"].value', [])


def reports(capfd, kind="Info"):
    return [line[len(kind) + 2:] for line in capfd.readouterr().out.splitlines()
            if line.startswith(kind + ": ")]


def write_csv(path, fps, frames, seed=0, head=None):
    """A take of `frames` rows at `fps` with random weights in every blend-shape column."""
    rng = np.random.default_rng(seed)
    weights = {name: np.round(rng.random(frames), 4) for name in ARKIT_BLENDSHAPES}
    zeros = np.zeros((frames, 3))
    write_take_csv(path, LiveLinkTake(np.arange(frames) / fps, weights,
                                      zeros if head is None else head, zeros, zeros, fps))
    return read_take_csv(path, fps)


# -- import ---------------------------------------------------------------------------------------

def test_import_keys_every_arkit_key_from_the_playhead(tmp_path, capfd):
    obj = add_avatar()
    set_fps(30)
    bpy.context.scene.frame_current = 10
    take = write_csv(tmp_path / "take.csv", 30, 5)
    assert bpy.ops.exclone.import_take_csv(filepath=str(tmp_path / "take.csv"),
                                           frame_rate=30) == {'FINISHED'}
    message = reports(capfd)[-1]
    assert message.startswith("Imported take.csv onto 'face': 5 frames at 30 fps (frames 10-14) "
                              "x 4 shape keys = 20 keyframes; 49 CSV columns have no shape key: "
                              "EyeLookDownLeft, EyeLookInLeft, EyeLookOutLeft, EyeLookUpLeft, ..."), message
    for column, arkit in COLUMNS.items():
        for name in ([arkit] if arkit != "browInnerUp" else ["browInnerUp_L", "browInnerUp_R"]):
            points = key_curve(obj, name)
            assert [frame for frame, _ in points] == list(range(10, 15)), name
            np.testing.assert_allclose([value for _, value in points], take.weights[arkit],
                                       atol=1e-6, err_msg=name)
    assert key_curve(obj, "smile") == [] and obj.animation_data is None
    # the keys show the take at the playhead
    assert obj.data.shape_keys.key_blocks["jawOpen"].value == pytest.approx(take.weights["jawOpen"][0],
                                                                            abs=1e-6)


def test_a_second_import_replaces_the_keys_at_its_frames_and_keeps_the_others(tmp_path):
    obj = add_avatar()
    set_fps(30)
    first = write_csv(tmp_path / "first.csv", 30, 6, seed=4)
    second = write_csv(tmp_path / "second.csv", 30, 4, seed=5)
    bpy.context.scene.frame_current = 1
    bpy.ops.exclone.import_take_csv(filepath=str(tmp_path / "first.csv"), frame_rate=30)
    bpy.context.scene.frame_current = 4
    bpy.ops.exclone.import_take_csv(filepath=str(tmp_path / "second.csv"), frame_rate=30)
    points = key_curve(obj, "eyeBlink_L")
    assert [frame for frame, _ in points] == list(range(1, 8))
    np.testing.assert_allclose([value for _, value in points],
                               np.concatenate([first.weights["eyeBlink_L"][:3],
                                               second.weights["eyeBlink_L"]]), atol=1e-6)


def test_import_at_another_scene_rate_resamples_the_take(tmp_path):
    obj = add_avatar()
    set_fps(24)
    bpy.context.scene.frame_current = 1
    take = write_csv(tmp_path / "take.csv", 60, 91, seed=1)       # 1.5 s at 60 fps
    # the frame rate is told from the timecodes, which cross a second
    assert bpy.ops.exclone.import_take_csv(filepath=str(tmp_path / "take.csv")) == {'FINISHED'}
    points = key_curve(obj, "jawOpen")
    assert [frame for frame, _ in points] == list(range(1, 1 + 37))   # 1.5 s at 24 fps
    expected = np.interp(np.arange(37) / 24, take.times, take.weights["jawOpen"])
    np.testing.assert_allclose([value for _, value in points], expected, atol=1e-6)


def test_import_turns_the_avatar_object_with_the_head(tmp_path):
    obj = add_avatar()
    set_fps(30)
    bpy.context.scene.frame_current = 1
    head = np.zeros((3, 3))
    head[1, 0] = math.pi / 4           # HeadYaw 0.25: 45 degrees to the head's own right
    write_csv(tmp_path / "take.csv", 30, 3, head=head)
    assert bpy.ops.exclone.import_take_csv(filepath=str(tmp_path / "take.csv"), frame_rate=30,
                                           head_target='OBJECT') == {'FINISHED'}
    assert obj.rotation_mode == 'QUATERNION'
    curves = keyframes(obj)
    assert set(curves) == {"rotation_quaternion"}
    assert [frame for frame, _ in curves["rotation_quaternion"]] == [1, 2, 3]
    bpy.context.scene.frame_set(2)
    forward = obj.rotation_quaternion @ Vector((0.0, -1.0, 0.0))
    assert forward.x == pytest.approx(-math.sqrt(0.5), abs=1e-5)      # the face looks to its right
    assert forward.y == pytest.approx(-math.sqrt(0.5), abs=1e-5)
    bpy.context.scene.frame_set(3)
    assert obj.rotation_quaternion.angle == pytest.approx(0.0, abs=1e-6)


# -- export ---------------------------------------------------------------------------------------

def test_export_writes_the_imported_columns_back(tmp_path, capfd):
    add_avatar()
    set_fps(30)
    bpy.context.scene.frame_current = 7
    take = write_csv(tmp_path / "take.csv", 30, 12, seed=2)
    bpy.ops.exclone.import_take_csv(filepath=str(tmp_path / "take.csv"), frame_rate=30)
    out = tmp_path / "out.csv"
    assert bpy.ops.exclone.export_take_csv(filepath=str(out), frame_range='KEYED') == {'FINISHED'}
    message = reports(capfd)[-1]
    assert message == ("Exported 'face' to out.csv: 12 frames (7-18) at 30 fps, 3 ARKit shapes "
                       "(head and eye rotations 0); 1 shape keys without an ARKit name skipped: "
                       "smile"), message
    assert out.read_text().splitlines()[0] == ",".join(HEADER)
    written = read_take_csv(out, 30)
    np.testing.assert_allclose(written.times, take.times, atol=1e-9)
    for arkit in COLUMNS.values():
        np.testing.assert_allclose(written.weights[arkit], take.weights[arkit], atol=1e-6)
    assert not written.weights["eyeBlink_R"].any() and not written.head.any()


def test_export_then_import_round_trips(tmp_path):
    obj = add_avatar()
    set_fps(25)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 3, 20
    rng = np.random.default_rng(3)
    written = {}
    for name in ARKIT_KEYS:
        block = obj.data.shape_keys.key_blocks[name]
        written[name] = rng.random(18)
        for frame, value in zip(range(3, 21), written[name]):
            block.value = value
            block.keyframe_insert("value", frame=frame)
    written["browInnerUp_R"] = written["browInnerUp_L"]      # one CSV column for both halves
    for frame, value in zip(range(3, 21), written["browInnerUp_R"]):
        obj.data.shape_keys.key_blocks["browInnerUp_R"].value = value
        obj.data.shape_keys.key_blocks["browInnerUp_R"].keyframe_insert("value", frame=frame)
    out = tmp_path / "out.csv"
    assert bpy.ops.exclone.export_take_csv(filepath=str(out)) == {'FINISHED'}   # scene range
    obj.data.shape_keys.animation_data_clear()
    scene.frame_current = 3
    assert bpy.ops.exclone.import_take_csv(filepath=str(out), frame_rate=25) == {'FINISHED'}
    for name in ARKIT_KEYS:
        points = key_curve(obj, name)
        assert [frame for frame, _ in points] == list(range(3, 21)), name
        np.testing.assert_allclose([value for _, value in points], written[name], atol=1e-6)


def test_export_of_the_last_take_uses_its_frames(tmp_path):
    obj = add_avatar()
    set_fps(30)
    take = write_csv(tmp_path / "take.csv", 30, 10)
    bpy.context.scene.frame_current = 1
    bpy.ops.exclone.import_take_csv(filepath=str(tmp_path / "take.csv"), frame_rate=30)
    with pytest.raises(RuntimeError, match="No recorded take on 'face': choose Scene Range"):
        bpy.ops.exclone.export_take_csv(filepath=str(tmp_path / "out.csv"), frame_range='TAKE')
    # a recorded take on this avatar that keyed frames 4-6 (as webcam_take.Take records them)
    webcam_take.last_take = type("RecordedTake", (), {"avatar": obj,
                                                      "tracked_frames": {0.1: 4, 0.2: 5, 0.3: 6}})
    assert bpy.ops.exclone.export_take_csv(filepath=str(tmp_path / "out.csv"),
                                           frame_range='TAKE') == {'FINISHED'}
    written = read_take_csv(tmp_path / "out.csv", 30)
    np.testing.assert_allclose(written.times, np.arange(3) / 30, atol=1e-9)
    np.testing.assert_allclose(written.weights["jawOpen"], take.weights["jawOpen"][3:6], atol=1e-6)


# -- bad input ------------------------------------------------------------------------------------

def test_bad_files_report_one_line_and_change_nothing(tmp_path):
    obj = add_avatar()
    set_fps(30)
    bad_header = tmp_path / "bad_header.csv"
    bad_header.write_text("Frame,Count,JawOpen\n1,61,0.5\n")
    bad_number = tmp_path / "bad_number.csv"
    write_csv(bad_number, 30, 3)
    lines = bad_number.read_text().splitlines()
    lines[2] = lines[2].replace(",61,", ",61x,", 1)
    bad_number.write_text("\n".join(lines))
    short = tmp_path / "short.csv"
    write_csv(short, 30, 3)
    cases = {str(tmp_path / "none.csv"): "not found: .*none.csv",
             str(bad_header): "bad_header.csv is not a Live Link Face CSV",
             str(bad_number): "bad_number.csv, line 3, column BlendShapeCount: '61x' is not a number",
             str(short): "unknown frame rate of short.csv"}
    for path, message in cases.items():
        with pytest.raises(RuntimeError, match=message):
            bpy.ops.exclone.import_take_csv(filepath=path, head_target='OBJECT')
    with pytest.raises(RuntimeError, match="'rig' is not an armature in this file"):
        bpy.ops.exclone.import_take_csv(filepath=str(short), frame_rate=30, head_target='BONE',
                                        armature="rig", bone="head")
    assert obj.data.shape_keys.animation_data is None and obj.animation_data is None
    assert obj.rotation_mode == 'XYZ'


def test_export_refuses_to_overwrite_unless_asked(tmp_path):
    obj = add_avatar()
    out = tmp_path / "out.csv"
    out.write_text("the user's file\n")
    with pytest.raises(RuntimeError, match="out.csv exists: turn on Overwrite to replace it"):
        bpy.ops.exclone.export_take_csv(filepath=str(out))
    assert out.read_text() == "the user's file\n"
    with pytest.raises(RuntimeError, match="'face' has no keyframes on its ARKit shape keys"):
        bpy.ops.exclone.export_take_csv(filepath=str(out), frame_range='KEYED', overwrite=True)
    assert out.read_text() == "the user's file\n"
    assert bpy.ops.exclone.export_take_csv(filepath=str(out), overwrite=True) == {'FINISHED'}
    obj.data.shape_keys.key_blocks["jawOpen"].value = 0.25
    assert bpy.ops.exclone.export_take_csv(filepath=str(out), overwrite=True) == {'FINISHED'}
    written = read_take_csv(out, 24)        # the factory scene: 24 fps, frames 1-250
    assert len(written.times) == 250     # unanimated keys are written with their constant value
    assert np.all(written.weights["jawOpen"] == 0.25) and np.all(written.weights["eyeBlink_L"] == 1)
    assert obj.data.shape_keys.animation_data is None


def test_the_operators_say_why_they_cannot_run():
    for name in ("import_take_csv", "export_take_csv"):
        with pytest.raises(RuntimeError, match="Nothing active"):
            getattr(bpy.ops.exclone, name)(filepath="take.csv")
    add_avatar("plain", keys=["smile", "frown"])
    for name in ("import_take_csv", "export_take_csv"):
        with pytest.raises(RuntimeError, match="'plain' has no shape keys with ARKit names"):
            getattr(bpy.ops.exclone, name)(filepath="take.csv")
    add_avatar()
    webcam_take.running = type("RunningTake", (), {"status": "tracking"})
    with pytest.raises(RuntimeError, match="A take is running"):
        bpy.ops.exclone.import_take_csv(filepath="take.csv")


def test_an_import_is_one_undo_step(tmp_path):
    """Background Blender pushes no undo step for an operator called from Python (the 'UNDO'
    option acts in the UI), so the steps are pushed by hand around it."""
    assert {'REGISTER', 'UNDO'} <= bpy.ops.exclone.import_take_csv.bl_options
    assert 'UNDO' not in bpy.ops.exclone.export_take_csv.bl_options    # it changes no data
    add_avatar()
    write_csv(tmp_path / "take.csv", 30, 4)
    window = bpy.context.window_manager.windows[0]
    with bpy.context.temp_override(window=window):
        bpy.ops.ed.undo_push(message="before")
        bpy.ops.exclone.import_take_csv(filepath=str(tmp_path / "take.csv"), frame_rate=30,
                                        head_target='OBJECT')
        bpy.ops.ed.undo_push(message="after")
        assert key_curve(bpy.data.objects["face"], "jawOpen")
        bpy.ops.ed.undo()
    obj = bpy.data.objects["face"]
    assert obj.data.shape_keys.animation_data is None and obj.animation_data is None
    assert obj.rotation_mode == 'XYZ'


def test_the_panel_offers_import_and_export_after_refine_take():
    webcam = bpy.context.scene.exclone.webcam
    webcam.head_target = 'OBJECT'
    log = []
    live_panel.draw(RecordingLayout(log), bpy.context)
    operators = [entry[1] for entry in log if entry[0] == "operator"]
    refine = operators.index("exclone.refine_take")
    assert operators[refine + 1:refine + 3] == ["exclone.import_take_csv", "exclone.export_take_csv"]
    assert ("label", "Not running") in log
