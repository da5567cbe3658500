"""Takes as Live Link Face CSV files: read one onto ARKit names, write one from them.

The format is what Epic's Live Link Face app records: a header row

    Timecode,BlendShapeCount,EyeBlinkLeft,EyeLookDownLeft,...,TongueOut,
    HeadYaw,HeadPitch,HeadRoll,LeftEyeYaw,LeftEyePitch,LeftEyeRoll,RightEyeYaw,RightEyePitch,RightEyeRoll

then one row per frame: the timecode HH:MM:SS:FF.fff (the time of day, FF the frame within the
second at the recording's frame rate, .fff a fraction of a frame; the rate itself is not in the
file), the count 61, the 52 blend-shape weights in [0, 1] and 9 head and eye rotations. The
rotations are normalised, 1 = 180 degrees: Unreal's ARKit face support (which the app streams
through) divides the rotator's degrees by 180. Column names are matched ignoring case (captures
spell the second column BlendShapeCount or BlendshapeCount); a file may lack some columns.

ExClone names the blend shapes by ARKit's raw values (core.library.ARKIT_BLENDSHAPES, e.g.
"eyeBlink_L"); SHAPE_COLUMNS is the one table between the two spellings. An avatar may split
browInnerUp and cheekPuff into halves (core.library.ARKIT_SPLIT): both halves take the column,
and a column is written from the mean of the halves.
"""
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from .errors import ExCloneError
from .library import ARKIT_SPLIT

# (CSV column, ARKit raw value) of the 52 blend shapes, in Live Link Face's column order.
SHAPE_COLUMNS = (
    ("EyeBlinkLeft", "eyeBlink_L"), ("EyeLookDownLeft", "eyeLookDown_L"),
    ("EyeLookInLeft", "eyeLookIn_L"), ("EyeLookOutLeft", "eyeLookOut_L"),
    ("EyeLookUpLeft", "eyeLookUp_L"), ("EyeSquintLeft", "eyeSquint_L"),
    ("EyeWideLeft", "eyeWide_L"), ("EyeBlinkRight", "eyeBlink_R"),
    ("EyeLookDownRight", "eyeLookDown_R"), ("EyeLookInRight", "eyeLookIn_R"),
    ("EyeLookOutRight", "eyeLookOut_R"), ("EyeLookUpRight", "eyeLookUp_R"),
    ("EyeSquintRight", "eyeSquint_R"), ("EyeWideRight", "eyeWide_R"),
    ("JawForward", "jawForward"), ("JawRight", "jawRight"), ("JawLeft", "jawLeft"),
    ("JawOpen", "jawOpen"), ("MouthClose", "mouthClose"), ("MouthFunnel", "mouthFunnel"),
    ("MouthPucker", "mouthPucker"), ("MouthRight", "mouthRight"), ("MouthLeft", "mouthLeft"),
    ("MouthSmileLeft", "mouthSmile_L"), ("MouthSmileRight", "mouthSmile_R"),
    ("MouthFrownLeft", "mouthFrown_L"), ("MouthFrownRight", "mouthFrown_R"),
    ("MouthDimpleLeft", "mouthDimple_L"), ("MouthDimpleRight", "mouthDimple_R"),
    ("MouthStretchLeft", "mouthStretch_L"), ("MouthStretchRight", "mouthStretch_R"),
    ("MouthRollLower", "mouthRollLower"), ("MouthRollUpper", "mouthRollUpper"),
    ("MouthShrugLower", "mouthShrugLower"), ("MouthShrugUpper", "mouthShrugUpper"),
    ("MouthPressLeft", "mouthPress_L"), ("MouthPressRight", "mouthPress_R"),
    ("MouthLowerDownLeft", "mouthLowerDown_L"), ("MouthLowerDownRight", "mouthLowerDown_R"),
    ("MouthUpperUpLeft", "mouthUpperUp_L"), ("MouthUpperUpRight", "mouthUpperUp_R"),
    ("BrowDownLeft", "browDown_L"), ("BrowDownRight", "browDown_R"),
    ("BrowInnerUp", "browInnerUp"), ("BrowOuterUpLeft", "browOuterUp_L"),
    ("BrowOuterUpRight", "browOuterUp_R"), ("CheekPuff", "cheekPuff"),
    ("CheekSquintLeft", "cheekSquint_L"), ("CheekSquintRight", "cheekSquint_R"),
    ("NoseSneerLeft", "noseSneer_L"), ("NoseSneerRight", "noseSneer_R"),
    ("TongueOut", "tongueOut"),
)
HEAD_COLUMNS = ("HeadYaw", "HeadPitch", "HeadRoll")
LEFT_EYE_COLUMNS = ("LeftEyeYaw", "LeftEyePitch", "LeftEyeRoll")
RIGHT_EYE_COLUMNS = ("RightEyeYaw", "RightEyePitch", "RightEyeRoll")
ROTATION_COLUMNS = HEAD_COLUMNS + LEFT_EYE_COLUMNS + RIGHT_EYE_COLUMNS
HEADER = ("Timecode", "BlendShapeCount") + tuple(c for c, _ in SHAPE_COLUMNS) + ROTATION_COLUMNS
BLENDSHAPE_COUNT = len(SHAPE_COLUMNS) + len(ROTATION_COLUMNS)     # 61, the second column
RADIANS_PER_UNIT = np.pi          # a rotation column's 1.0 is 180 degrees
# Frame rates the timecodes may count at; one is told from a take's timecodes when not given.
FRAME_RATES = (24, 25, 30, 48, 50, 60)
SUBFRAME_DIGITS = 3               # FF.fff
_DAY = 24 * 3600.0


@dataclass
class LiveLinkTake:
    """A take: T frames at `times` (seconds from its first frame, increasing)."""
    times: np.ndarray             # (T,)
    weights: dict                 # ARKit raw value (e.g. "eyeBlink_L") -> (T,) weights
    head: np.ndarray              # (T, 3) yaw, pitch, roll in radians
    left_eye: np.ndarray          # (T, 3) yaw, pitch, roll in radians
    right_eye: np.ndarray         # (T, 3) yaw, pitch, roll in radians
    frame_rate: float             # the rate the timecodes count frames at


def read_take_csv(path, frame_rate=None):
    """The take in a Live Link Face CSV file. frame_rate: the rate its timecodes count frames at
    (the file does not say); None tells it from the timecodes, which needs a take that crosses a
    second. ExCloneError for a wrong header, a bad number or timecode, timecodes that do not
    increase, or a frame rate the timecodes contradict or do not reveal."""
    path = Path(path)
    header, body = _header_and_rows(path)
    columns = _checked_columns(path, header)
    _check_row_lengths(path, body, len(header))
    numbers = _numbers(path, header, body)
    codes = np.array([line.split(",", 1)[0].strip() for line in body])
    clock, frames = _timecode_fields(path, codes)
    rate = _frame_rate(path, codes, frames, frame_rate)
    times = _checked_times(path, codes, clock + frames / rate)

    def column(name):
        return numbers[:, columns[name] - 1] if name in columns else np.zeros(len(body))

    def angles(names):
        return np.column_stack([column(name) for name in names]) * RADIANS_PER_UNIT

    weights = {arkit: column(name) for name, arkit in SHAPE_COLUMNS if name in columns}
    return LiveLinkTake(times, weights, angles(HEAD_COLUMNS), angles(LEFT_EYE_COLUMNS),
                        angles(RIGHT_EYE_COLUMNS), float(rate))


def write_take_csv(path, take):
    """Writes `take` with every column of HEADER (weights it lacks as 0), timecodes from
    00:00:00:00 at round(take.frame_rate) frames a second, numbers to 9 significant digits."""
    times = np.asarray(take.times, dtype=float)
    rate = round(take.frame_rate) if np.isfinite(take.frame_rate) else 0
    if rate < 1:
        raise ExCloneError(f"cannot write timecodes at {take.frame_rate} frames a second")
    if times.ndim != 1 or not len(times) or not np.all(np.isfinite(times)) or times[0] < 0 \
            or np.any(np.diff(times) <= 0):
        raise ExCloneError("a take's times must be increasing seconds from 0 on")
    unknown = sorted(set(take.weights) - {arkit for _, arkit in SHAPE_COLUMNS})
    if unknown:
        raise ExCloneError(f"not ARKit blend shapes: {', '.join(unknown)}")
    zeros = np.zeros(len(times))
    shapes = [np.asarray(take.weights.get(arkit, zeros), dtype=float) for _, arkit in SHAPE_COLUMNS]
    rotations = np.column_stack([take.head, take.left_eye, take.right_eye]) / RADIANS_PER_UNIT
    numbers = np.column_stack([np.full(len(times), BLENDSHAPE_COUNT)] + shapes + [rotations])
    lines = [",".join(HEADER)]
    lines += [code + "," + ",".join(np.char.mod("%.9g", row))
              for code, row in zip(timecodes(times, rate), numbers)]
    try:
        Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")
    except OSError as exc:
        raise ExCloneError(f"cannot write {path}: {exc.strerror or exc}") from exc


def resampled(take, frame_rate):
    """The take at frame_rate frames a second from its first frame to (about) its last: every
    column interpolated linearly in time."""
    count = int(round(take.times[-1] * frame_rate)) + 1
    times = np.arange(count) / frame_rate

    def at(values):
        return np.interp(times, take.times, values)

    def angles(values):
        return np.column_stack([at(column) for column in np.asarray(values).T])

    return LiveLinkTake(times, {name: at(values) for name, values in take.weights.items()},
                        angles(take.head), angles(take.left_eye), angles(take.right_eye),
                        frame_rate)


def timecodes(times, frame_rate):
    """HH:MM:SS:FF.fff of `times` (seconds) at an integer frame rate."""
    # whole thousandths of a frame, so that rounding carries into the frame, second and hour
    ticks = np.rint(np.asarray(times) * frame_rate * 10 ** SUBFRAME_DIGITS).astype(np.int64)
    frames, fraction = np.divmod(ticks, 10 ** SUBFRAME_DIGITS)
    seconds, frame = np.divmod(frames, frame_rate)
    minutes, second = np.divmod(seconds, 60)
    hour, minute = np.divmod(minutes, 60)
    return [f"{h % 24:02d}:{m:02d}:{s:02d}:{f:02d}.{x:03d}"
            for h, m, s, f, x in zip(hour, minute, second, frame, fraction)]


def head_rotations(head):
    """Rotations in Blender's axes (a face looking along -Y, +Z up, +X its left) of (T, 3) yaw,
    pitch and roll in radians, read as Unreal's rotator applied to the head: yaw > 0 turns it to
    its own right, pitch > 0 lifts the chin, roll > 0 tilts it towards its right shoulder; yaw is
    the outermost rotation. (Not checked against a recording of known motion.)"""
    return Rotation.from_euler("ZXY", -np.asarray(head, dtype=float))


def keys_for_columns(key_names):
    """({CSV column: [the avatar's keys it drives]}, [columns that drive none]) for an avatar's
    shape-key names: a key named by the column's ARKit name, and the _L/_R halves of a split
    shape."""
    names = set(key_names)
    driven, unmatched = {}, []
    for column, arkit in SHAPE_COLUMNS:
        keys = [key for key in (arkit,) + ARKIT_SPLIT.get(arkit, ()) if key in names]
        if keys:
            driven[column] = keys
        else:
            unmatched.append(column)
    return driven, unmatched


def weights_from_keys(values):
    """{ARKit raw value: (T,) weights} for a take from {shape-key name: (T,) values}: the key
    named by the ARKit name, else the mean of its _L/_R halves; keys of other names are left
    out."""
    driven, _ = keys_for_columns(values)
    weights = {}
    for column, arkit in SHAPE_COLUMNS:
        keys = driven.get(column, [])
        chosen = [arkit] if arkit in keys else keys
        if chosen:
            weights[arkit] = np.mean([values[key] for key in chosen], axis=0)
    return weights


def _header_and_rows(path):
    if not path.is_file():
        raise ExCloneError(f"not found: {path}")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise ExCloneError(f"cannot read {path}: {exc}") from exc
    lines = [line for line in text.splitlines() if line.strip()]
    if len(lines) < 2:
        raise ExCloneError(f"{path.name} holds no frames: a Live Link Face CSV has a header row "
                           "and one row per frame")
    return [name.strip() for name in lines[0].split(",")], lines[1:]


def _checked_columns(path, header):
    """{known column name: its index in the file}, after checking the header."""
    if [name.lower() for name in header[:2]] != ["timecode", "blendshapecount"]:
        raise ExCloneError(f"{path.name} is not a Live Link Face CSV: its header starts with "
                           f"{','.join(header[:2])!r}, not 'Timecode,BlendShapeCount'")
    known = {name.lower(): name for name in HEADER[2:]}
    unknown = [name for name in header[2:] if name.lower() not in known]
    if unknown:
        raise ExCloneError(f"{path.name}: unknown column(s) {', '.join(unknown[:5])} (a Live Link "
                           "Face CSV has the 52 ARKit blend shapes and the head and eye rotations)")
    lowered = [name.lower() for name in header]
    repeated = sorted({known[name] for name in lowered[2:] if lowered.count(name) > 1})
    if repeated:
        raise ExCloneError(f"{path.name}: column(s) {', '.join(repeated)} appear more than once")
    columns = {known[name.lower()]: index for index, name in enumerate(header) if index >= 2}
    if not any(name in columns for name, _ in SHAPE_COLUMNS):
        raise ExCloneError(f"{path.name} has no blend-shape columns (e.g. EyeBlinkLeft, JawOpen)")
    return columns


def _check_row_lengths(path, body, count):
    lengths = np.char.count(np.array(body), ",") + 1
    short = np.flatnonzero(lengths != count)
    if len(short):
        row = short[0]
        raise ExCloneError(f"{path.name}, line {row + 2}: {lengths[row]} fields where the header "
                           f"has {count} (a truncated or damaged row)")


def _numbers(path, header, body):
    """(T, columns - 1) floats of every column after the timecode, checked finite."""
    arguments = dict(delimiter=",", usecols=range(1, len(header)), comments=None, ndmin=2)
    try:
        numbers = np.loadtxt(body, **arguments)
    except ValueError:      # a cell that is not a number: genfromtxt leaves it NaN, named below
        numbers = np.genfromtxt(body, dtype=float, **arguments)
    bad = np.argwhere(~np.isfinite(numbers))
    if len(bad):
        row, column = bad[0] + (0, 1)
        text = body[row].split(",")[column].strip()
        raise ExCloneError(f"{path.name}, line {row + 2}, column {header[column]}: {text!r} is "
                           "not a number")
    return numbers


def _timecode_fields(path, codes):
    """(the whole seconds as seconds of the day, the frames with their fraction) of
    HH:MM:SS:FF.fff timecodes."""
    shaped = np.char.count(codes, ":") == 3
    fields = np.full((len(codes), 4), np.nan)
    if shaped.any():
        fields[shaped] = np.genfromtxt(np.char.replace(codes[shaped], ":", ","), delimiter=",",
                                       dtype=float, comments=None, ndmin=2)
    clock = fields[:, :3]
    valid = np.isfinite(fields).all(axis=1) & (fields >= 0).all(axis=1) \
        & (clock == np.floor(clock)).all(axis=1) & (clock[:, 1:] < 60).all(axis=1)
    bad = np.flatnonzero(~valid)
    if len(bad):
        raise ExCloneError(f"{path.name}, line {bad[0] + 2}: timecode {str(codes[bad[0]])!r} is not "
                           "HH:MM:SS:FF.fff")
    return clock @ np.array([3600.0, 60.0, 1.0]), fields[:, 3]


def _frame_rate(path, codes, frames, frame_rate):
    """The rate the timecodes count at: the one given, checked against the frame numbers, or
    the smallest of FRAME_RATES above them when the take crosses a second."""
    top = int(np.argmax(frames))
    if frame_rate is not None:
        if not np.isfinite(frame_rate) or frame_rate <= 0:
            raise ExCloneError(f"the CSV's frame rate must be positive, not {frame_rate}")
        if np.floor(frames[top]) >= round(frame_rate):
            raise ExCloneError(f"{path.name}, line {top + 2}: timecode {codes[top]} counts frame "
                               f"{int(frames[top])}, past {frame_rate:g} fps: set the CSV's frame "
                               "rate to the one it was recorded at")
        return round(frame_rate)
    crosses_a_second = np.any(np.diff(frames) < 0)
    above = [rate for rate in FRAME_RATES if rate > np.floor(frames[top])]
    if not crosses_a_second or not above:
        why = ("its take is shorter than a second" if not crosses_a_second else
               f"timecode {codes[top]} counts frame {int(frames[top])}, past {FRAME_RATES[-1]} fps")
        raise ExCloneError(f"unknown frame rate of {path.name} ({why}): give the frame rate it "
                           "was recorded at")
    return above[0]


def _checked_times(path, codes, clock):
    """Seconds from the first frame, a take across midnight made continuous; increasing."""
    days = np.concatenate([[0], np.cumsum(np.diff(clock) < -_DAY / 2)])
    times = clock + days * _DAY
    times = times - times[0]
    back = np.flatnonzero(np.diff(times) <= 0)
    if len(back):
        row = back[0] + 1
        raise ExCloneError(f"{path.name}, line {row + 2}: timecode {codes[row]} does not come "
                           f"after {codes[row - 1]} (the timecodes must increase)")
    return times
