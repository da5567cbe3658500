"""Drive from Webcam: the tracked face drives the active mesh's shape keys (and a head rotation).

One frame's work is Take.step(): read a frame, track it (core.live), write the shape-key values
and the head rotation, key them when recording, update the camera preview image. The modal
operator calls step() on a window-manager timer; execute() (scripts, background Blender) and the
tests call it in a loop. Everything a take changes is one undo step: the operator finishes once,
when the take ends.

The preview is an image datablock, "ExClone Camera" (the frame downscaled, the landmarks drawn
in LANDMARK_COLOUR), drawn in the viewport's corner by a gpu draw handler that exists only while
a take runs in a window.
"""
from collections import OrderedDict
from pathlib import Path

import bpy
import cv2
import numpy as np
from bpy_extras import anim_utils
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, StringProperty
from mathutils import Matrix, Quaternion

from ..core import capture
from ..core import live as core_live
from ..core.errors import ExCloneError
from ..core.library import ARKIT_BLENDSHAPES, ARKIT_SPLIT
from ..core.tracking import Camera
from . import mesh_io, preferences, workflow
from .properties import HEAD_TARGET_ITEMS, KEY_SET_ITEMS, WEBCAM_SOURCE_ITEMS

PREVIEW_IMAGE = "ExClone Camera"
PREVIEW_WIDTH = 320
LANDMARK_COLOUR = (0, 255, 0)          # RGB: pure green is rare in camera images
ARKIT_NAMES = frozenset(ARKIT_BLENDSHAPES) | {half for pair in ARKIT_SPLIT.values() for half in pair}
RIG_CACHE_SIZE = 2

running = None        # the Take in progress in the UI (the Stop and Calibrate operators act on it)
last_take = None      # the last take that recorded keyframes (Refine Take rewrites them)


# -- the avatar -----------------------------------------------------------------------------------

_rigs = OrderedDict()


def checked_avatar(obj):
    if obj is None:
        raise ExCloneError("Nothing active: make the avatar head (a mesh with shape keys) the "
                           "active object")
    if obj.type != 'MESH':
        raise ExCloneError(f"'{obj.name}' is not a mesh: the avatar must be a mesh with shape keys")
    if not workflow.has_shape_keys(obj):
        raise ExCloneError(f"'{obj.name}' has no shape keys besides the basis: add expressions "
                           "first (e.g. Generate ARKit Shapes)")
    return obj


def avatar_keys(obj, key_set):
    """(names, deltas) of the shape keys a take drives: every non-basis key, or the ARKit ones."""
    names, deltas = mesh_io.shape_keys_from_object(checked_avatar(obj), what="avatar")
    if key_set == 'ARKIT':
        rows = [i for i, name in enumerate(names) if name in ARKIT_NAMES]
        if not rows:
            raise ExCloneError(f"'{obj.name}' has no shape keys with ARKit names (e.g. jawOpen, "
                               "eyeBlink_L): choose All Shape Keys")
        names, deltas = [names[i] for i in rows], deltas[rows]
    return names, deltas


def avatar_rig(obj, key_set, progress=None):
    """The avatar's core.live.AvatarRig, from a small cache: locating the tracker's face on the
    avatar is a registration (seconds), redone only when the mesh or its keys change."""
    names, deltas = avatar_keys(obj, key_set)
    mesh = workflow.basis_mesh(obj, "avatar")
    key = workflow.digest(mesh.vertices, mesh.loop_totals, mesh.loop_vertices, deltas, names)
    if key in _rigs:
        _rigs.move_to_end(key)
        return _rigs[key]
    try:
        rig = core_live.AvatarRig.from_arrays(mesh.vertices, mesh.triangles(), deltas, names,
                                             progress=progress)
    except ExCloneError as exc:
        raise ExCloneError(f"'{obj.name}': the tracker's face does not register onto this "
                           f"avatar ({exc})") from exc
    workflow.remember(_rigs, key, rig, RIG_CACHE_SIZE)
    return rig


# -- head rotation --------------------------------------------------------------------------------

class HeadTarget:
    """The object or pose bone that follows the head, in quaternion rotation mode.

    The tracker's head rotation is in world axes for something facing -Y; it is turned into the
    holder's own parent space (for a bone: its rest orientation in the armature, parent bones'
    poses aside) and applied on top of the rotation the holder had when the take started."""

    def __init__(self, owner, pose_bone=None):
        self.owner, self.holder = owner, pose_bone or owner
        # Blender converts the current rotation when the mode changes: the pose stays as it is.
        self.holder.rotation_mode = 'QUATERNION'
        self.rest = self.holder.rotation_quaternion.copy()
        if pose_bone is None:
            parent_space = owner.parent.matrix_world @ owner.matrix_parent_inverse \
                if owner.parent is not None else Matrix.Identity(4)
        else:
            parent_space = owner.matrix_world @ pose_bone.bone.matrix_local
        self.space = parent_space.to_quaternion()
        self.path = "rotation_quaternion"

    def describe(self):
        return self.owner.name if self.holder is self.owner else \
            f"bone '{self.holder.name}' of '{self.owner.name}'"

    def apply(self, head_rotation):
        x, y, z, w = head_rotation.as_quat()
        world = Quaternion((w, x, y, z))
        local = self.space.inverted() @ world @ self.space
        self.holder.rotation_quaternion = local @ self.rest

    def keyframe(self, frame):
        self.holder.keyframe_insert(self.path, frame=frame)


def head_holder(kind, avatar, armature_name, bone_name):
    """(owner, pose bone or None) that the head rotation goes onto, or None; checks only."""
    if kind == 'NONE':
        return None
    if kind == 'OBJECT':
        return avatar, None
    armature = bpy.data.objects.get(armature_name) if armature_name else None
    if armature is None or armature.type != 'ARMATURE':
        raise ExCloneError("Head rotation onto a bone: choose an armature" if not armature_name
                           else f"'{armature_name}' is not an armature in this file")
    bone = armature.pose.bones.get(bone_name)
    if bone is None:
        raise ExCloneError(f"Armature '{armature.name}' has no bone '{bone_name}'")
    return armature, bone


# -- the camera ------------------------------------------------------------------------------------

def calibrated_camera(webcam, frame_size):
    """The scene's chessboard intrinsics scaled to this source's frame size, or None."""
    if not webcam.calibrated or webcam.calibration_width <= 0 or webcam.calibration_height <= 0:
        return None
    sx = frame_size[0] / webcam.calibration_width
    sy = frame_size[1] / webcam.calibration_height
    # pixel centres: (c + 0.5) scales with the image
    return Camera(webcam.fx * sx, webcam.fy * sy, (webcam.cx + 0.5) * sx - 0.5,
                  (webcam.cy + 0.5) * sy - 0.5)


def source_spec(context, source_type, camera_index, filepath):
    """What capture.open_source opens for these choices; ExCloneError for an empty or wrong path."""
    if source_type == 'CAMERA':
        return camera_index if camera_index >= 0 else preferences.camera_index(context)
    kind = "video file" if source_type == 'VIDEO' else "image folder"
    if not filepath:
        raise ExCloneError(f"Choose a {kind} to track")
    path = Path(bpy.path.abspath(filepath))
    if source_type == 'VIDEO' and path.is_dir():
        raise ExCloneError(f"{path} is a folder: choose Image Folder as the source")
    if source_type == 'FOLDER' and path.is_file():
        raise ExCloneError(f"{path} is a file: choose Video File as the source")
    return str(path)


# -- one take --------------------------------------------------------------------------------------

class Take:
    """A take's state: the avatar, the frame source, the tracking session and what it wrote.

    step() does one frame; it returns False once the take is over (end of the file, camera lost,
    stop requested, max_frames reached), with the reason in end_reason."""

    def __init__(self, scene, avatar, names, source, session, record=False, head=None,
                 max_frames=0):
        self.scene, self.avatar, self.names = scene, avatar, list(names)
        self.avatar_name = avatar.name      # for the report, even if the avatar goes away
        self.source, self.session, self.record, self.head = source, session, record, head
        self.max_frames = max_frames
        self.start_frame = scene.frame_current
        self.frames_read = self.frames_with_face = 0
        # timestamp -> scene frame of the frames keyed from a tracked face (Refine rewrites them)
        self.tracked_frames = {}
        self.time_zero = None         # a camera's take starts at its first keyed frame
        self.status = f"starting: {source.description}"
        self.end_reason = None
        self.camera_lost = False
        self.stop_requested = False

    @property
    def fps(self):
        render = self.scene.render
        return render.fps / render.fps_base

    def scene_frame(self, timestamp):
        """frame = start + round(t * fps): a file's own time, a camera's time since keying began."""
        if self.source.is_live:
            if self.time_zero is None:
                self.time_zero = timestamp
            timestamp -= self.time_zero
        return self.start_frame + round(timestamp * self.fps)

    def step(self):
        if self.stop_requested:
            self.end_reason = "stopped"
            return False
        if self.max_frames and self.frames_read >= self.max_frames:
            self.end_reason = f"{self.max_frames} frames read"
            return False
        try:
            frame = self.source.read()
        except capture.CameraLost as exc:
            self.end_reason = f"{exc}: the take ended"
            self.camera_lost = True
            return False
        if frame is None:
            self.end_reason = "the source ended"
            return False
        result = self.session.step(frame.image, frame.timestamp)
        self.frames_read += 1
        self.frames_with_face += bool(result.found)
        self.status = result.status
        # Without a face the session repeats the last pose: it is held (and keyed) as it was.
        if result.weights is not None:
            self._write(result, frame.timestamp)
        update_preview(frame.image, result.landmarks if result.found else None)
        return True

    def _write(self, result, timestamp):
        key_blocks = self.avatar.data.shape_keys.key_blocks
        frame = self.scene_frame(timestamp) if self.record else None
        for name in self.names:
            block = key_blocks[name]
            block.value = min(max(result.weights[name], 0.0), 1.0)
            if frame is not None:
                block.keyframe_insert("value", frame=frame)
        if self.head is not None and result.head_rotation is not None:
            self.head.apply(result.head_rotation)
            if frame is not None:
                self.head.keyframe(frame)
        if frame is not None and result.found:
            self.tracked_frames[round(float(timestamp), 6)] = frame

    def close(self):
        self.source.close()

    def summary(self):
        text = f"{self.frames_read} frames from {self.source.description}, " \
               f"{self.frames_with_face} with a face"
        if self.record:
            frames = sorted(self.tracked_frames.values())
            text += f", keyed at frames {frames[0]}-{frames[-1]}" if frames else ", nothing keyed"
        return text


def take_report(take):
    """(report type, one line) for a finished take."""
    text = f"Take on '{take.avatar_name}': {take.summary()}"
    if take.camera_lost:
        return {'WARNING'}, f"{take.end_reason}; {text} (what was recorded is kept)"
    return {'INFO'}, f"{text} ({take.end_reason}; last status: {take.status})"


def start_take(context, *, source_type, camera_index=-1, filepath="", record=False, key_set='ALL',
               head_kind='NONE', armature="", bone="", max_frames=0, use_calibration=True,
               progress=None):
    """Checks the avatar and the head target, prepares the avatar (cached), then opens the
    source: a Take ready to step. Raises ExCloneError with nothing changed."""
    avatar = checked_avatar(context.active_object)
    spec = source_spec(context, source_type, camera_index, filepath)
    holder = head_holder(head_kind, avatar, armature, bone)
    rig = avatar_rig(avatar, key_set, progress=progress)
    source = capture.open_source(spec)
    try:
        webcam = context.scene.exclone.webcam
        camera = calibrated_camera(webcam, source.frame_size) if use_calibration else None
        # The session calibrates the neutral face over the first second by itself.
        session = core_live.FaceTrackingSession(
            avatar=rig, camera=camera, calibration_frames=max(1, round(source.frame_rate or 30)))
    except BaseException:
        source.close()
        raise
    if holder is not None:
        context.view_layer.update()         # world matrices of objects moved by scripts
    head = HeadTarget(*holder) if holder is not None else None
    return Take(context.scene, avatar, rig.names, source, session, record=record, head=head,
                max_frames=max_frames)


# -- the preview image -----------------------------------------------------------------------------

def update_preview(image_bgr, landmarks=None):
    """The frame at PREVIEW_WIDTH pixels wide with the landmarks as 2x2 dots, into the
    PREVIEW_IMAGE datablock (made or resized as needed)."""
    height, width = image_bgr.shape[:2]
    scale = PREVIEW_WIDTH / width
    size = (PREVIEW_WIDTH, max(1, round(height * scale)))
    rgb = cv2.cvtColor(cv2.resize(image_bgr, size, interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2RGB)
    if landmarks is not None:
        points = np.rint((np.asarray(landmarks)[:, :2] + 0.5) * scale - 0.5).astype(int)
        for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
            x = np.clip(points[:, 0] + dx, 0, size[0] - 1)
            y = np.clip(points[:, 1] + dy, 0, size[1] - 1)
            rgb[y, x] = LANDMARK_COLOUR
    rgba = np.ones((size[1], size[0], 4), dtype=np.float32)
    rgba[..., :3] = rgb[::-1] / 255.0          # Blender's images start at the bottom row
    image = bpy.data.images.get(PREVIEW_IMAGE)
    if image is None:
        image = bpy.data.images.new(PREVIEW_IMAGE, size[0], size[1])
    elif tuple(image.size) != size:
        image.scale(*size)
    image.pixels.foreach_set(rgba.ravel())
    image.update()
    return image


def _draw_overlay():
    """Viewport draw handler (only registered while a take runs in a window): the preview image
    in the region's bottom-right corner, with the take's status above it."""
    import blf
    import gpu
    from gpu_extras.presets import draw_texture_2d

    image = bpy.data.images.get(PREVIEW_IMAGE)
    take = running
    if image is None or take is None:
        return
    region = bpy.context.region
    width, height = image.size
    x, y = region.width - width - 20, 20
    draw_texture_2d(gpu.texture.from_image(image), (x, y), width, height)
    blf.position(0, x, y + height + 8, 0)
    blf.size(0, 13)
    blf.draw(0, f"ExClone: {take.status}")


def shape_key_curves(key):
    """{data path: F-curve} of a shape-key datablock's action (its slot's channel bag)."""
    animation = key.animation_data
    if animation is None or animation.action is None:
        return {}
    if not hasattr(animation, "action_slot"):       # Blender before 4.4: no slots
        curves = animation.action.fcurves
    else:
        bag = anim_utils.action_get_channelbag_for_slot(animation.action, animation.action_slot)
        curves = bag.fcurves if bag is not None else []
    return {curve.data_path: curve for curve in curves}


# -- operators -------------------------------------------------------------------------------------

def _poll_avatar(cls, context):
    if context.mode != 'OBJECT':
        cls.poll_message_set("Switch to Object Mode first")
        return False
    try:
        checked_avatar(context.active_object)
    except ExCloneError as exc:
        cls.poll_message_set(str(exc))
        return False
    return True


class EXCLONE_OT_drive_from_webcam(bpy.types.Operator):
    """Track a face from a webcam, a video file or a folder of images and drive the active
    mesh's shape keys with it (Esc or Stop ends the take; everything it did is one undo step)"""
    bl_idname = "exclone.drive_from_webcam"
    bl_label = "Drive from Webcam"
    bl_options = {'REGISTER', 'UNDO'}

    source_type: EnumProperty(name="Source", items=WEBCAM_SOURCE_ITEMS, default="CAMERA")
    camera_index: IntProperty(name="Camera", min=-1, max=63, default=-1,
                              description="-1: the webcam chosen in the add-on preferences")
    filepath: StringProperty(name="Path", subtype='FILE_PATH',
                             description="The video file or the image folder")
    record: BoolProperty(name="Record", default=False,
                         description="Insert keyframes at scene frames that follow the take's time")
    key_set: EnumProperty(name="Shape Keys", items=KEY_SET_ITEMS, default="ALL")
    head_target: EnumProperty(name="Head Rotation", items=HEAD_TARGET_ITEMS, default="NONE")
    armature: StringProperty(name="Armature", description="Armature object of the head bone")
    bone: StringProperty(name="Bone", description="Bone that follows the head")
    max_frames: IntProperty(name="Max Frames", min=0, default=0,
                            description="Stop after this many frames (0: until the source ends "
                                        "or Esc)")
    use_calibration: BoolProperty(
        name="Use Camera Calibration", default=True,
        description="Use the scene's chessboard calibration when there is one")
    show_overlay: BoolProperty(name="Camera Preview", default=True,
                               description="Show the camera image in the viewport while tracking")

    @classmethod
    def poll(cls, context):
        if running is not None:
            cls.poll_message_set("A take is running: Esc or Stop ends it")
            return False
        return _poll_avatar(cls, context)

    def _start(self, context):
        window_manager = context.window_manager
        window_manager.progress_begin(0.0, 1.0)
        try:
            return start_take(
                context, source_type=self.source_type, camera_index=self.camera_index,
                filepath=self.filepath, record=self.record, key_set=self.key_set,
                head_kind=self.head_target, armature=self.armature, bone=self.bone,
                max_frames=self.max_frames, use_calibration=self.use_calibration,
                progress=lambda fraction, *_: window_manager.progress_update(fraction))
        finally:
            window_manager.progress_end()

    def execute(self, context):
        try:
            take = self._start(context)
        except ExCloneError as exc:
            self.report({'ERROR'}, str(exc))
            return {'CANCELLED'}
        try:
            while take.step():
                pass
        finally:
            take.close()
        return self._finish(take)

    def invoke(self, context, event):
        global running
        if bpy.app.background or context.window is None:
            return self.execute(context)
        try:
            take = self._start(context)
        except ExCloneError as exc:
            self.report({'ERROR'}, str(exc))
            return {'CANCELLED'}
        running = self._take = take
        window_manager = context.window_manager
        self._timer = window_manager.event_timer_add(1 / 120, window=context.window)
        self._overlay = bpy.types.SpaceView3D.draw_handler_add(
            _draw_overlay, (), 'WINDOW', 'POST_PIXEL') if self.show_overlay else None
        window_manager.modal_handler_add(self)
        context.workspace.status_text_set(f"ExClone: {take.status} (Esc stops the take)")
        return {'RUNNING_MODAL'}

    def modal(self, context, event):
        take = self._take
        if event.type == 'ESC' and event.value == 'PRESS':
            take.stop_requested = True
        elif event.type != 'TIMER':     # the view stays usable while the take runs
            return {'PASS_THROUGH'}
        try:
            going = take.step()
        except ReferenceError:      # the avatar was deleted or an undo replaced it
            take.end_reason = "the avatar was removed during the take"
            going = False
        if going:
            context.workspace.status_text_set(f"ExClone: {take.status} (Esc stops the take)")
            for area in context.screen.areas:
                if area.type == 'VIEW_3D':
                    area.tag_redraw()
            return {'RUNNING_MODAL'}
        return self._end_modal(context)

    def _end_modal(self, context):
        global running
        context.window_manager.event_timer_remove(self._timer)
        if self._overlay is not None:
            bpy.types.SpaceView3D.draw_handler_remove(self._overlay, 'WINDOW')
        context.workspace.status_text_set(None)
        for area in context.screen.areas:
            area.tag_redraw()
        running = None
        self._take.close()
        return self._finish(self._take)

    def _finish(self, take):
        global last_take
        if take.record and take.tracked_frames:
            last_take = take
        self.report(*take_report(take))
        return {'FINISHED'}


class _RunningTake:
    """Operators on the take in progress; they change no data, so they push no undo step (one
    would split the take's own)."""
    bl_options = {'REGISTER'}

    @classmethod
    def poll(cls, context):
        if running is None:
            cls.poll_message_set("No take is running: start Drive from Webcam first")
            return False
        return True


class EXCLONE_OT_stop_webcam(_RunningTake, bpy.types.Operator):
    """End the running take (everything it did stays, as one undo step)"""
    bl_idname = "exclone.stop_webcam"
    bl_label = "Stop"

    def execute(self, context):
        running.stop_requested = True
        return {'FINISHED'}


class EXCLONE_OT_calibrate_neutral(_RunningTake, bpy.types.Operator):
    """Restart the neutral-face calibration of the running take: hold a neutral face for a
    second"""
    bl_idname = "exclone.calibrate_neutral"
    bl_label = "Calibrate"

    def execute(self, context):
        running.session.calibrate()
        running.status = "calibrating: hold a neutral face"
        self.report({'INFO'}, f"Calibrating over the next {running.session.calibration_frames} "
                              "frames with a face: hold a neutral face")
        return {'FINISHED'}


class EXCLONE_OT_refine_take(bpy.types.Operator):
    """Refine the last recorded take: jointly improve the avatar's blendshapes as the tracker
    sees them and the weights over the whole take, and rewrite its keyframes"""
    bl_idname = "exclone.refine_take"
    bl_label = "Refine Take"
    bl_options = {'REGISTER', 'UNDO'}

    closeness: FloatProperty(name="Closeness", min=0.0, default=1.0,
                             description="How close the refined blendshapes stay to the initial "
                                         "ones (higher: closer)")
    iterations: IntProperty(name="Iterations", min=1, max=200, default=20)

    @classmethod
    def poll(cls, context):
        if running is not None:
            cls.poll_message_set("A take is running: Esc or Stop ends it")
            return False
        try:
            usable = last_take is not None and last_take.avatar.name in bpy.data.objects
        except ReferenceError:
            usable = False
        if not usable:
            cls.poll_message_set("Record a take first (Refine works on the last recorded take)")
            return False
        return True

    def execute(self, context):
        take = last_take
        try:
            timestamps, weights, names = take.session.refine_take(self.closeness, self.iterations)
        except ExCloneError as exc:
            self.report({'ERROR'}, str(exc))
            return {'CANCELLED'}
        frames = [take.tracked_frames.get(round(float(t), 6)) for t in timestamps]
        rows = [i for i, frame in enumerate(frames) if frame is not None]
        key = take.avatar.data.shape_keys
        curves = shape_key_curves(key)
        changes = []
        for j, name in enumerate(names):
            block = key.key_blocks.get(name)
            if block is None:           # renamed or removed since the take
                continue
            curve = curves.get(f'key_blocks["{name}"].value')
            for i in rows:
                value = min(max(float(weights[i, j]), 0.0), 1.0)
                if curve is not None:
                    changes.append(abs(value - curve.evaluate(frames[i])))
                block.value = value
                block.keyframe_insert("value", frame=frames[i])
        context.scene.frame_set(context.scene.frame_current)
        change = f", mean change {np.mean(changes):.3f}" if changes else ""
        self.report({'INFO'}, f"Refined {len(rows)} frames of the take on "
                              f"'{take.avatar.name}'{change}")
        return {'FINISHED'}


class EXCLONE_OT_calibrate_camera(bpy.types.Operator):
    """Compute the webcam's intrinsics from views of a printed chessboard (a folder of photos or
    frames grabbed from the camera) and store them in the scene for later takes"""
    bl_idname = "exclone.calibrate_camera"
    bl_label = "Calibrate Camera"
    bl_options = {'REGISTER', 'UNDO'}

    directory: StringProperty(name="Chessboard Folder", subtype='DIR_PATH')
    camera_frames: IntProperty(
        name="Camera Frames", min=0, max=200, default=0,
        description="0: read the folder; N: grab N frames (every 10th) from the camera instead")
    camera_index: IntProperty(name="Camera", min=-1, max=63, default=-1,
                              description="-1: the webcam chosen in the add-on preferences")
    columns: IntProperty(name="Inner Corners X", min=3, max=30, default=9)
    rows: IntProperty(name="Inner Corners Y", min=3, max=30, default=6)

    def _images(self, context):
        if self.camera_frames:
            spec = source_spec(context, 'CAMERA', self.camera_index, "")
            with capture.open_source(spec) as source:
                frames = [source.read() for _ in range(10 * self.camera_frames)]
            return [frame.image for frame in frames[::10]]
        spec = source_spec(context, 'FOLDER', -1, self.directory)
        with capture.open_source(spec) as source:
            return [frame.image for frame in source]

    def execute(self, context):
        try:
            images = self._images(context)
            camera, rms = core_live.calibrate_camera(images, (self.columns, self.rows))
        except ExCloneError as exc:
            self.report({'ERROR'}, str(exc))
            return {'CANCELLED'}
        webcam = context.scene.exclone.webcam
        height, width = images[0].shape[:2]
        webcam.fx, webcam.fy, webcam.cx, webcam.cy = camera.fx, camera.fy, camera.cx, camera.cy
        webcam.calibration_width, webcam.calibration_height = width, height
        webcam.calibration_rms = rms
        webcam.calibrated = True
        self.report({'INFO'}, f"Camera calibrated from {len(images)} images ({width} x {height}): "
                              f"fx {camera.fx:.1f}, fy {camera.fy:.1f}, centre ({camera.cx:.1f}, "
                              f"{camera.cy:.1f}), reprojection error {rms:.2f} px")
        return {'FINISHED'}


CLASSES = (EXCLONE_OT_drive_from_webcam, EXCLONE_OT_stop_webcam, EXCLONE_OT_calibrate_neutral,
           EXCLONE_OT_refine_take, EXCLONE_OT_calibrate_camera)
register, unregister = bpy.utils.register_classes_factory(CLASSES)
