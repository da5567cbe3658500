"""Takes travel as Live Link Face CSV files (core.livelink_csv): Import Take CSV keys one onto the
active avatar's ARKit-named shape keys (and optionally its head rotation) from the playhead, at
the scene's frame rate; Export Take CSV writes the avatar's shape-key animation as one.

Both check everything (the avatar, the file, the head target) before they change anything, and
report what they did, or why not, in one line.
"""
from pathlib import Path

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, FloatProperty, StringProperty
from bpy_extras.io_utils import ExportHelper, ImportHelper

from ..core import livelink_csv
from ..core.errors import ExCloneError
from ..core.reports import listed
from . import webcam_take
from .avatar_rig import checked_avatar
from .head_motion import HeadTarget, head_holder
from .live_operators import poll_avatar, poll_no_take
from .properties import HEAD_TARGET_ITEMS
from .reporting import passes, reporting

FRAME_RANGE_ITEMS = [
    ("SCENE", "Scene Range", "The scene's start to end frame"),
    ("TAKE", "Last Take", "The frames the last recorded webcam take keyed on this avatar"),
    ("KEYED", "Keyed Frames", "The avatar's first to last shape-key keyframe"),
]


def arkit_keys(obj):
    """({CSV column: [shape keys it drives]}, [columns that drive none]) of a checked avatar;
    ExCloneError when no key has an ARKit name."""
    names = [block.name for block in checked_avatar(obj).data.shape_keys.key_blocks[1:]]
    driven, unmatched = livelink_csv.keys_for_columns(names)
    if not driven:
        raise ExCloneError(f"'{obj.name}' has no shape keys with ARKit names (e.g. jawOpen, "
                           "eyeBlink_L): a take's CSV columns are ARKit blend shapes")
    return driven, unmatched


def scene_fps(scene):
    return scene.render.fps / scene.render.fps_base


def _poll_arkit_avatar(cls, context):
    return (poll_no_take(cls) and poll_avatar(cls, context)
            and passes(cls, arkit_keys, context.active_object))


# -- import ---------------------------------------------------------------------------------------

def import_take(context, filepath, frame_rate=0.0, head_kind='NONE', armature="", bone=""):
    """Keys the CSV's take onto the active avatar from the playhead; returns the report line.
    Everything is read and checked first: an ExCloneError changes nothing."""
    avatar = context.active_object
    driven, unmatched = arkit_keys(avatar)
    holder = head_holder(head_kind, avatar, armature, bone)
    path = Path(bpy.path.abspath(filepath))
    take = livelink_csv.read_take_csv(path, frame_rate or None)
    scene = context.scene
    fps = scene_fps(scene)
    take = livelink_csv.resampled(take, fps)
    frames = scene.frame_current + np.arange(len(take.times))
    arkit = dict(livelink_csv.SHAPE_COLUMNS)
    keyed = _key_shapes(avatar.data.shape_keys, {
        name: take.weights[arkit[column]] for column, names in driven.items()
        if arkit[column] in take.weights for name in names}, frames)
    text = (f"Imported {path.name} onto '{avatar.name}': {len(frames)} frames at {fps:g} fps "
            f"(frames {frames[0]}-{frames[-1]}) x {len(keyed)} shape keys = "
            f"{len(frames) * len(keyed)} keyframes")
    if holder is not None:
        context.view_layer.update()         # world matrices of objects moved by scripts
        _key_head(HeadTarget(*holder), livelink_csv.head_rotations(take.head), frames)
        text += ", head rotation keyed"
    scene.frame_set(scene.frame_current)
    no_key = [column for column in unmatched if arkit[column] in take.weights]
    if no_key:
        text += f"; {len(no_key)} CSV columns have no shape key: {listed(no_key)}"
    return text


def _key_shapes(key, values, frames):
    """Keys each shape key in `values` ({name: (T,) values}) at `frames`; returns the names."""
    for name in values:
        # keyframe_insert makes the F-curve (its action, slot and channel bag, whatever the
        # Blender version); the points then go straight onto it
        key.key_blocks[name].keyframe_insert("value", frame=int(frames[0]))
    curves = webcam_take.shape_key_curves(key)
    for name, series in values.items():
        block = key.key_blocks[name]
        curve = curves[f'key_blocks["{name}"].value']
        points = curve.keyframe_points
        clipped = np.clip(series, block.slider_min, block.slider_max)
        if len(points) == 1:        # a new F-curve: every point at once (a long take in seconds)
            points.add(len(frames) - 1)
            points.foreach_set("co", np.column_stack([frames, clipped]).ravel().astype(np.float32))
        else:                       # keys of its own: the take's replace those at its frames
            for frame, value in zip(frames, clipped):
                points.insert(int(frame), float(value), options={'FAST'})
        curve.update()              # sorted, handles recomputed
    return list(values)


def _key_head(head, rotations, frames):
    for rotation, frame in zip(rotations, frames):
        head.apply(rotation)
        head.keyframe(int(frame))


class EXCLONE_OT_import_take_csv(bpy.types.Operator, ImportHelper):
    """Key a Live Link Face CSV take onto the active avatar's ARKit-named shape keys (and
    optionally its head rotation) from the playhead, at the scene's frame rate (one undo step)"""
    bl_idname = "exclone.import_take_csv"
    bl_label = "Import Take CSV"
    bl_options = {'REGISTER', 'UNDO'}

    filename_ext = ".csv"
    filter_glob: StringProperty(default="*.csv", options={'HIDDEN'})
    frame_rate: FloatProperty(
        name="CSV Frame Rate", min=0.0, max=1000.0, default=0.0,
        description="The frame rate the CSV was recorded at (its timecodes count frames at it); "
                    "0: tell it from the timecodes of a take longer than a second")
    head_target: EnumProperty(name="Head Rotation", items=HEAD_TARGET_ITEMS, default="NONE")
    armature: StringProperty(name="Armature", description="Armature object of the head bone")
    bone: StringProperty(name="Bone", description="Bone that follows the head")

    @classmethod
    def poll(cls, context):
        return _poll_arkit_avatar(cls, context)

    @reporting
    def execute(self, context):
        # nothing is keyed before the file and the avatar are checked
        text = import_take(context, self.filepath, self.frame_rate, self.head_target,
                           self.armature, self.bone)
        self.report({'INFO'}, text)
        return {'FINISHED'}


# -- export ---------------------------------------------------------------------------------------

def export_take(context, filepath, frame_range='SCENE', overwrite=False):
    """Writes the active avatar's ARKit-named shape keys over `frame_range` at the scene's frame
    rate to a CSV; returns the report line. ExCloneError, with nothing written, on bad input."""
    avatar = context.active_object
    driven, _ = arkit_keys(avatar)
    path = Path(bpy.path.abspath(filepath))
    if path.is_dir() or not path.name:
        raise ExCloneError(f"{path} is a folder: choose a file name for the CSV")
    if path.exists() and not overwrite:
        raise ExCloneError(f"{path} exists: turn on Overwrite to replace it")
    key = avatar.data.shape_keys
    frames = _export_frames(context.scene, avatar, driven, frame_range)
    names = [name for names in driven.values() for name in names]
    weights = livelink_csv.weights_from_keys(_key_values(key, names, frames))
    fps = scene_fps(context.scene)
    still = np.zeros((len(frames), 3))
    livelink_csv.write_take_csv(path, livelink_csv.LiveLinkTake(
        (frames - frames[0]) / fps, weights, still, still, still, fps))
    skipped = [block.name for block in key.key_blocks[1:] if block.name not in names]
    text = (f"Exported '{avatar.name}' to {path.name}: {len(frames)} frames "
            f"({frames[0]}-{frames[-1]}) at {fps:g} fps, {len(weights)} ARKit shapes "
            "(head and eye rotations 0)")
    if skipped:
        text += f"; {len(skipped)} shape keys without an ARKit name skipped: {listed(skipped)}"
    return text


def _export_frames(scene, avatar, driven, frame_range):
    """The scene frames to write, first to last."""
    if frame_range == 'SCENE':
        first, last = scene.frame_start, scene.frame_end
    elif frame_range == 'TAKE':
        take = webcam_take.last_take
        try:
            frames = sorted(take.tracked_frames.values()) \
                if take is not None and take.avatar == avatar else []
        except ReferenceError:      # the take's avatar is gone
            frames = []
        if not frames:
            raise ExCloneError(f"No recorded take on '{avatar.name}': choose Scene Range or "
                               "Keyed Frames")
        first, last = frames[0], frames[-1]
    else:
        curves = webcam_take.shape_key_curves(avatar.data.shape_keys)
        keyed = [point.co[0] for names in driven.values() for name in names
                 for point in getattr(curves.get(f'key_blocks["{name}"].value'),
                                      "keyframe_points", ())]
        if not keyed:
            raise ExCloneError(f"'{avatar.name}' has no keyframes on its ARKit shape keys: "
                               "choose Scene Range")
        first, last = round(min(keyed)), round(max(keyed))
    return np.arange(first, last + 1)


def _key_values(key, names, frames):
    """{shape-key name: (T,) its value at each frame}: its F-curve's, else its constant value."""
    curves = webcam_take.shape_key_curves(key)
    values = {}
    for name in names:
        curve = curves.get(f'key_blocks["{name}"].value')
        values[name] = np.array([curve.evaluate(float(frame)) for frame in frames]) \
            if curve is not None else np.full(len(frames), key.key_blocks[name].value)
    return values


class EXCLONE_OT_export_take_csv(bpy.types.Operator, ExportHelper):
    """Write the active avatar's ARKit-named shape-key animation as a Live Link Face CSV at the
    scene's frame rate (keys without an ARKit name are skipped)"""
    bl_idname = "exclone.export_take_csv"
    bl_label = "Export Take CSV"
    bl_options = {'REGISTER'}

    filename_ext = ".csv"
    filter_glob: StringProperty(default="*.csv", options={'HIDDEN'})
    frame_range: EnumProperty(name="Frames", items=FRAME_RANGE_ITEMS, default="SCENE")
    overwrite: BoolProperty(name="Overwrite", default=False,
                            description="Replace the file if it exists")

    @classmethod
    def poll(cls, context):
        return _poll_arkit_avatar(cls, context)

    @reporting
    def execute(self, context):
        # nothing is written before the avatar and the path are checked
        text = export_take(context, self.filepath, self.frame_range, self.overwrite)
        self.report({'INFO'}, text)
        return {'FINISHED'}


CLASSES = (EXCLONE_OT_import_take_csv, EXCLONE_OT_export_take_csv)
register, unregister = bpy.utils.register_classes_factory(CLASSES)
