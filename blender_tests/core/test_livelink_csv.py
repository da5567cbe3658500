"""core.livelink_csv: Live Link Face CSV takes read and written.

- the column table against ARKit's 52 names, and the header in Live Link Face's layout;
- write -> read gives the same times, weights and rotations, with the frame rate told from the
  timecodes or given;
- a hand-written three-row file in the real header layout reads to known values (seconds,
  ARKit names, radians);
- timecodes: carries, midnight, frame rates; resampling; the head's axes;
- bad files (header, numbers, rows, timecodes, frame rates) are ExCloneErrors that say where.
"""
import numpy as np
import pytest

from exclone_addon.core import livelink_csv
from exclone_addon.core.errors import ExCloneError
from exclone_addon.core.library import ARKIT_BLENDSHAPES, ARKIT_SPLIT
from exclone_addon.core.livelink_csv import (LiveLinkTake, read_take_csv, resampled,
                                             timecodes, write_take_csv)

# The header row of a Live Link Face recording, written out here rather than taken from the module.
REAL_HEADER = (
    "Timecode,BlendShapeCount,EyeBlinkLeft,EyeLookDownLeft,EyeLookInLeft,EyeLookOutLeft,"
    "EyeLookUpLeft,EyeSquintLeft,EyeWideLeft,EyeBlinkRight,EyeLookDownRight,EyeLookInRight,"
    "EyeLookOutRight,EyeLookUpRight,EyeSquintRight,EyeWideRight,JawForward,JawRight,JawLeft,"
    "JawOpen,MouthClose,MouthFunnel,MouthPucker,MouthRight,MouthLeft,MouthSmileLeft,"
    "MouthSmileRight,MouthFrownLeft,MouthFrownRight,MouthDimpleLeft,MouthDimpleRight,"
    "MouthStretchLeft,MouthStretchRight,MouthRollLower,MouthRollUpper,MouthShrugLower,"
    "MouthShrugUpper,MouthPressLeft,MouthPressRight,MouthLowerDownLeft,MouthLowerDownRight,"
    "MouthUpperUpLeft,MouthUpperUpRight,BrowDownLeft,BrowDownRight,BrowInnerUp,BrowOuterUpLeft,"
    "BrowOuterUpRight,CheekPuff,CheekSquintLeft,CheekSquintRight,NoseSneerLeft,NoseSneerRight,"
    "TongueOut,HeadYaw,HeadPitch,HeadRoll,LeftEyeYaw,LeftEyePitch,LeftEyeRoll,RightEyeYaw,"
    "RightEyePitch,RightEyeRoll")


def csv_row(timecode, columns=REAL_HEADER, **values):
    """A data row: `values` ({column: text}) in their columns, "0" elsewhere, the count 61."""
    names = columns.split(",")[2:]
    return ",".join([timecode, "61"] + [values.get(name, "0") for name in names])


def write(tmp_path, lines, name="take.csv"):
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def random_take(frames, fps, seed=0):
    rng = np.random.default_rng(seed)
    weights = {name: rng.random(frames) for name in ARKIT_BLENDSHAPES}
    angles = [rng.uniform(-0.6, 0.6, (frames, 3)) for _ in range(3)]
    return LiveLinkTake(np.arange(frames) / fps, weights, *angles, fps)


def assert_same_take(read, take, times_tolerance=1e-9):
    np.testing.assert_allclose(read.times, take.times, rtol=0, atol=times_tolerance)
    assert set(read.weights) == set(take.weights)
    for name, values in take.weights.items():
        np.testing.assert_allclose(read.weights[name], values, rtol=0, atol=1e-6, err_msg=name)
    for part in ("head", "left_eye", "right_eye"):
        np.testing.assert_allclose(getattr(read, part), getattr(take, part), rtol=0, atol=1e-6)


# -- the format -----------------------------------------------------------------------------------

def test_the_column_table_covers_arkits_52_shapes_in_live_link_faces_layout():
    columns = [column for column, _ in livelink_csv.SHAPE_COLUMNS]
    names = [name for _, name in livelink_csv.SHAPE_COLUMNS]
    assert sorted(names) == sorted(ARKIT_BLENDSHAPES) and len(set(columns)) == 52
    assert ",".join(livelink_csv.HEADER) == REAL_HEADER
    assert livelink_csv.BLENDSHAPE_COUNT == 61 == len(livelink_csv.HEADER) - 2


# -- round trips ----------------------------------------------------------------------------------

@pytest.mark.parametrize("fps, given", [(60, None), (30, 30), (24, None), (25, 25.0)])
def test_write_then_read_gives_the_same_take(tmp_path, fps, given):
    take = random_take(2 * fps + 7, fps)       # over two seconds: the rate shows in the timecodes
    path = tmp_path / "take.csv"
    write_take_csv(path, take)
    lines = path.read_text().splitlines()
    assert lines[0] == REAL_HEADER and len(lines) == len(take.times) + 1
    assert lines[1].startswith("00:00:00:00.000,61,")
    assert lines[fps + 1].startswith("00:00:01:00.000,61,")
    read = read_take_csv(path, given)
    assert read.frame_rate == fps
    assert_same_take(read, take)


def test_times_off_the_frame_grid_come_back_to_a_thousandth_of_a_frame(tmp_path):
    fps = 60
    take = random_take(90, fps, seed=1)
    take.times = take.times + np.random.default_rng(2).uniform(0, 0.4 / fps, 90)
    take.times[0] = 0.0
    write_take_csv(tmp_path / "take.csv", take)
    read = read_take_csv(tmp_path / "take.csv", fps)
    assert_same_take(read, take, times_tolerance=0.5e-3 / fps + 1e-12)


def test_a_take_written_at_a_fractional_scene_rate_keeps_its_real_times(tmp_path):
    fps = 30000 / 1001                          # NTSC: timecodes count 30 frames a second
    take = random_take(100, fps, seed=3)
    write_take_csv(tmp_path / "take.csv", take)
    read = read_take_csv(tmp_path / "take.csv", fps)
    assert read.frame_rate == 30
    assert_same_take(read, take, times_tolerance=0.5e-3 / 30 + 1e-12)
    assert np.array_equal(np.rint(read.times * fps), np.arange(100))


def test_a_take_with_only_some_weights_writes_the_others_as_zero(tmp_path):
    take = LiveLinkTake(np.arange(3) / 30, {"jawOpen": np.array([0.1, 0.2, 0.3])},
                        *[np.zeros((3, 3))] * 3, 30)
    write_take_csv(tmp_path / "take.csv", take)
    read = read_take_csv(tmp_path / "take.csv", 30)
    assert len(read.weights) == 52
    np.testing.assert_allclose(read.weights["jawOpen"], [0.1, 0.2, 0.3])
    assert all(not values.any() for name, values in read.weights.items() if name != "jawOpen")


# -- a hand-written file --------------------------------------------------------------------------

def test_a_hand_written_three_row_file_reads_to_known_values(tmp_path):
    path = write(tmp_path, [
        REAL_HEADER,
        csv_row("14:03:52:28.500", EyeBlinkLeft="0.1", JawRight="0.25", JawLeft="0.05",
                BrowInnerUp="0.75", HeadYaw="0.25", LeftEyePitch="-0.05"),
        csv_row("14:03:52:29.500", EyeBlinkLeft="0.2", JawRight="0.5", MouthLeft="1",
                HeadYaw="0.125"),
        csv_row("14:03:53:00.500", EyeBlinkLeft="0.3", TongueOut="0.9", HeadRoll="-0.5",
                RightEyeYaw="1e-2"),
    ])
    take = read_take_csv(path, 30)
    assert take.frame_rate == 30
    np.testing.assert_allclose(take.times, [0, 1 / 30, 2 / 30], atol=1e-12)
    assert len(take.weights) == 52
    expected = {"eyeBlink_L": [0.1, 0.2, 0.3], "jawRight": [0.25, 0.5, 0], "jawLeft": [0.05, 0, 0],
                "browInnerUp": [0.75, 0, 0], "mouthLeft": [0, 1, 0], "tongueOut": [0, 0, 0.9]}
    for name, values in expected.items():
        np.testing.assert_allclose(take.weights[name], values, err_msg=name)
    assert not take.weights["eyeBlink_R"].any() and not take.weights["mouthRight"].any()
    # rotations: 1.0 in the file is 180 degrees
    np.testing.assert_allclose(take.head, [[np.pi / 4, 0, 0], [np.pi / 8, 0, 0], [0, 0, -np.pi / 2]])
    np.testing.assert_allclose(take.left_eye[:, 1], [-0.05 * np.pi, 0, 0])
    np.testing.assert_allclose(take.right_eye[:, 0], [0, 0, 0.01 * np.pi])
    # crossing a second shows the rate: frame 29 is the last of 30
    assert read_take_csv(path).frame_rate == 30


def test_other_spellings_and_a_subset_of_the_columns_are_read(tmp_path):
    header = "timecode,BlendshapeCount,JAWOPEN,EyeBlinkRight,HeadPitch"
    path = write(tmp_path, [
        header,
        "00:00:10:05,61,0.5,0.25,0.1",
        "00:00:10:06.250,61,0.75,0.125,-0.1",
    ])
    take = read_take_csv(path, 60)
    np.testing.assert_allclose(take.times, [0, 1.25 / 60])
    assert set(take.weights) == {"jawOpen", "eyeBlink_R"}
    np.testing.assert_allclose(take.weights["jawOpen"], [0.5, 0.75])
    np.testing.assert_allclose(take.head, [[0, 0.1 * np.pi, 0], [0, -0.1 * np.pi, 0]])
    assert not take.left_eye.any() and not take.right_eye.any()
    # a byte-order mark before the header (spreadsheet exports) is no part of the first name
    path.write_text("\ufeff" + path.read_text(), encoding="utf-8")
    assert set(read_take_csv(path, 60).weights) == {"jawOpen", "eyeBlink_R"}


# -- timecodes, resampling, head axes -------------------------------------------------------------

def test_timecodes_carry_into_the_second_minute_and_hour():
    assert timecodes([0, 1 / 60, 59.99999 / 60, 59.5 / 60, 3599 + 59 / 60, 3600.0], 60) == [
        "00:00:00:00.000", "00:00:00:01.000", "00:00:01:00.000", "00:00:00:59.500",
        "00:59:59:59.000", "01:00:00:00.000"]


def test_a_take_across_midnight_goes_on_in_time(tmp_path):
    path = write(tmp_path, [REAL_HEADER, csv_row("23:59:59:28"), csv_row("23:59:59:29"),
                            csv_row("00:00:00:00"), csv_row("00:00:00:01")])
    np.testing.assert_allclose(read_take_csv(path, 30).times, np.arange(4) / 30, atol=1e-9)


def test_resampling_keeps_the_frames_on_both_grids_and_interpolates_between():
    take = random_take(121, 60, seed=4)
    half = resampled(take, 30)
    np.testing.assert_allclose(half.times, np.arange(61) / 30)
    np.testing.assert_allclose(half.weights["jawOpen"], take.weights["jawOpen"][::2], atol=1e-12)
    np.testing.assert_allclose(half.head, take.head[::2], atol=1e-12)
    double = resampled(half, 60)
    np.testing.assert_allclose(double.weights["jawOpen"][::2], half.weights["jawOpen"], atol=1e-12)
    middle = (half.weights["jawOpen"][:-1] + half.weights["jawOpen"][1:]) / 2
    np.testing.assert_allclose(double.weights["jawOpen"][1::2], middle, atol=1e-12)


def test_head_angles_turn_the_head_about_its_own_axes():
    forward, up = np.array([0.0, -1.0, 0.0]), np.array([0.0, 0.0, 1.0])   # its right is -X
    yaw, pitch, roll = livelink_csv.head_rotations(np.diag([0.3, 0.3, 0.3]))
    assert yaw.apply(forward)[0] < -0.29 and abs(yaw.apply(up) - up).max() < 1e-12   # to its right
    assert pitch.apply(forward)[2] > 0.29 and abs(pitch.apply(forward)[0]) < 1e-12   # chin up
    assert roll.apply(up)[0] < -0.29 and abs(roll.apply(forward) - forward).max() < 1e-12
    assert np.allclose([r.magnitude() for r in (yaw, pitch, roll)], 0.3)
    # yaw is the outermost rotation, roll the innermost
    both = livelink_csv.head_rotations([[0.3, 0.2, 0.1]])[0]
    alone = livelink_csv.head_rotations([[0.3, 0, 0], [0, 0.2, 0], [0, 0, 0.1]])
    assert (both * (alone[0] * alone[1] * alone[2]).inv()).magnitude() < 1e-12


# -- avatars' keys --------------------------------------------------------------------------------

def test_split_halves_take_their_column_and_are_written_as_their_mean():
    names = ["Basis", "jawOpen", "browInnerUp_L", "browInnerUp_R", "cheekPuff", "cheekPuff_L",
             "smile"]
    driven, unmatched = livelink_csv.keys_for_columns(names)
    assert driven == {"JawOpen": ["jawOpen"], "BrowInnerUp": ["browInnerUp_L", "browInnerUp_R"],
                      "CheekPuff": ["cheekPuff", "cheekPuff_L"]}
    assert len(unmatched) == 49 and "EyeBlinkLeft" in unmatched
    assert set(ARKIT_SPLIT) == {"browInnerUp", "cheekPuff"}
    values = {name: np.full(2, float(i)) for i, name in enumerate(names)}
    weights = livelink_csv.weights_from_keys(values)
    assert set(weights) == {"jawOpen", "browInnerUp", "cheekPuff"}
    np.testing.assert_allclose(weights["browInnerUp"], [2.5, 2.5])     # mean of its halves
    np.testing.assert_allclose(weights["cheekPuff"], [4, 4])           # its own key first


# -- bad files ------------------------------------------------------------------------------------

def test_a_wrong_header_is_refused_with_what_is_wrong(tmp_path):
    row = csv_row("00:00:00:00")
    cases = {
        "Frame,BlendShapeCount,JawOpen": "not a Live Link Face CSV: its header starts with "
                                         "'Frame,BlendShapeCount'",
        "Timecode,BlendShapeCount,JawOpen,Smile": r"unknown column\(s\) Smile",
        "Timecode,BlendShapeCount,JawOpen,jawopen": r"column\(s\) JawOpen appear more than once",
        "Timecode,BlendShapeCount,HeadYaw": "has no blend-shape columns",
    }
    for header, message in cases.items():
        width = len(header.split(","))
        path = write(tmp_path, [header, ",".join(row.split(",")[:width])])
        with pytest.raises(ExCloneError, match=message):
            read_take_csv(path, 30)
    with pytest.raises(ExCloneError, match="holds no frames"):
        read_take_csv(write(tmp_path, [REAL_HEADER]), 30)
    with pytest.raises(ExCloneError, match="not found: .*none.csv"):
        read_take_csv(tmp_path / "none.csv", 30)


@pytest.mark.parametrize("row, message", [
    (csv_row("00:00:00:01", JawOpen="0.5x"), "line 3, column JawOpen: '0.5x' is not a number"),
    (csv_row("00:00:00:01", HeadRoll="nan"), "line 3, column HeadRoll: 'nan' is not a number"),
    (csv_row("00:00:00:01", MouthLeft=""), "line 3, column MouthLeft: '' is not a number"),
    (csv_row("00:00:00:01").rsplit(",", 3)[0], "line 3: 60 fields where the header has 63"),
    (csv_row("00:00:01"), "line 3: timecode '00:00:01' is not HH:MM:SS:FF.fff"),
    (csv_row("00:61:00:01"), "line 3: timecode '00:61:00:01' is not HH:MM:SS:FF.fff"),
    (csv_row("00:00:00.5:01"), "line 3: timecode '00:00:00.5:01' is not HH:MM:SS:FF.fff"),
    (csv_row("ab:00:00:01"), "line 3: timecode 'ab:00:00:01' is not HH:MM:SS:FF.fff"),
    (csv_row("00:00:00:00"), "line 3: timecode 00:00:00:00 does not come after 00:00:00:00.900"),
    (csv_row("00:00:00:00.5"), "line 3: timecode 00:00:00:00.5 does not come after 00:00:00:00.900"),
])
def test_bad_numbers_rows_and_timecodes_are_refused_where_they_are(tmp_path, row, message):
    path = write(tmp_path, [REAL_HEADER, csv_row("00:00:00:00.900"), row])
    with pytest.raises(ExCloneError, match=message.replace("(", r"\(").replace(")", r"\)")):
        read_take_csv(path, 30)


def test_an_unknown_or_contradicted_frame_rate_is_refused(tmp_path):
    short = write(tmp_path, [REAL_HEADER] + [csv_row(f"10:00:00:{f:02d}") for f in range(5)])
    with pytest.raises(ExCloneError, match="unknown frame rate of take.csv \\(its take is shorter "
                                           "than a second\\): give the frame rate"):
        read_take_csv(short)
    assert read_take_csv(short, 24).frame_rate == 24
    sixty = write(tmp_path, [REAL_HEADER] + [csv_row(f"10:00:00:{f:02d}") for f in (40, 59)]
                  + [csv_row("10:00:01:00")], "sixty.csv")
    assert read_take_csv(sixty).frame_rate == 60
    with pytest.raises(ExCloneError, match="line 3: timecode 10:00:00:59 counts frame 59, past "
                                           "30 fps: set the CSV's frame rate"):
        read_take_csv(sixty, 30)
    fast = write(tmp_path, [REAL_HEADER, csv_row("10:00:00:99"), csv_row("10:00:01:00")], "fast.csv")
    with pytest.raises(ExCloneError, match="counts frame 99, past 60 fps"):
        read_take_csv(fast)
    for rate in (0.0, -24.0, float("nan")):
        with pytest.raises(ExCloneError, match="frame rate must be positive"):
            read_take_csv(short, rate)


def test_writing_refuses_what_is_not_a_take(tmp_path):
    take = random_take(3, 30)
    with pytest.raises(ExCloneError, match="not ARKit blend shapes: smile"):
        write_take_csv(tmp_path / "a.csv", LiveLinkTake(take.times, {"smile": np.zeros(3)},
                                                        take.head, take.left_eye, take.right_eye, 30))
    for times in ([0.0, 0.1, 0.1], [-0.1, 0.0, 0.1], [0.0, np.nan, 0.2]):
        with pytest.raises(ExCloneError, match="increasing seconds from 0 on"):
            write_take_csv(tmp_path / "a.csv", LiveLinkTake(np.array(times), take.weights,
                                                            take.head, take.left_eye,
                                                            take.right_eye, 30))
    with pytest.raises(ExCloneError, match="cannot write timecodes at 0.2 frames a second"):
        write_take_csv(tmp_path / "a.csv", LiveLinkTake(take.times, take.weights, take.head,
                                                        take.left_eye, take.right_eye, 0.2))
    with pytest.raises(ExCloneError, match="cannot write .*missing"):
        write_take_csv(tmp_path / "missing" / "a.csv", take)
    assert not (tmp_path / "a.csv").exists()
