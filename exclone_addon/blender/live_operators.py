"""The webcam operators: Drive from Webcam (a take, modal in a window, a loop in execute()), Stop
and Calibrate on the running take, Refine Take on the last recorded one, Calibrate Camera.

Every error reaches the user as one line (blender.reporting): before a take starts
nothing changes; an error during a take ends it, and what it recorded stays as one undo step.
"""
import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, StringProperty

from ..core import capture
from ..core.camera_calibration import calibrate_camera
from . import camera_preview, webcam_take
from .avatar_rig import checked_avatar
from .properties import (APPEARANCE_OPTION, HEAD_TARGET_ITEMS, KEY_SET_ITEMS,
                         WEBCAM_SOURCE_ITEMS)
from .reporting import failed, in_object_mode, passes, reporting


def poll_avatar(cls, context):
    return in_object_mode(cls, context) and passes(cls, checked_avatar, context.active_object)


def poll_no_take(cls):
    if webcam_take.running is not None:
        cls.poll_message_set("A take is running: Esc or Stop ends it")
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
    use_appearance: BoolProperty(**APPEARANCE_OPTION)

    @classmethod
    def poll(cls, context):
        return poll_no_take(cls) and poll_avatar(cls, context)

    def _start(self, context):
        """The Take, or None after reporting why it could not start (nothing changed)."""
        window_manager = context.window_manager
        window_manager.progress_begin(0.0, 1.0)
        try:
            return webcam_take.start_take(
                context, source_type=self.source_type, camera_index=self.camera_index,
                filepath=self.filepath, record=self.record, key_set=self.key_set,
                head_kind=self.head_target, armature=self.armature, bone=self.bone,
                max_frames=self.max_frames, use_calibration=self.use_calibration,
                use_appearance=self.use_appearance,
                progress=lambda fraction, *_: window_manager.progress_update(fraction))
        except Exception as exc:    # whatever stops the start, the user reads one line
            failed(self, exc)
            return None
        finally:
            window_manager.progress_end()

    def execute(self, context):
        take = self._start(context)
        if take is None:
            return {'CANCELLED'}
        try:
            while take.step():
                pass
        finally:
            take.close()
        return self._finish(take)

    def invoke(self, context, event):
        if bpy.app.background or context.window is None:
            return self.execute(context)
        take = self._start(context)
        if take is None:
            return {'CANCELLED'}
        webcam_take.running = self._take = take
        take.start_worker()         # reading and tracking leave the main thread from here
        window_manager = context.window_manager
        self._timer = window_manager.event_timer_add(1 / 120, window=context.window)
        self._overlay = camera_preview.show_overlay(take) if self.show_overlay else None
        window_manager.modal_handler_add(self)
        context.workspace.status_text_set(f"ExClone: {take.status} (Esc stops the take)")
        return {'RUNNING_MODAL'}

    def modal(self, context, event):
        take = self._take
        if event.type == 'ESC' and event.value == 'PRESS':
            take.stop_requested = True
        elif event.type != 'TIMER':     # the view stays usable while the take runs
            return {'PASS_THROUGH'}
        applied = take.frames_read
        if not take.tick():
            return self._end_modal(context)
        if take.frames_read != applied:     # a new frame was applied: show it
            context.workspace.status_text_set(f"ExClone: {take.status} (Esc stops the take)")
            for area in context.screen.areas:
                if area.type == 'VIEW_3D':
                    area.tag_redraw()
        return {'RUNNING_MODAL'}

    def _end_modal(self, context):
        context.window_manager.event_timer_remove(self._timer)
        if self._overlay is not None:
            camera_preview.hide_overlay(self._overlay)
        context.workspace.status_text_set(None)
        for area in context.screen.areas:
            area.tag_redraw()
        webcam_take.running = None
        self._take.close()
        return self._finish(self._take)

    def _finish(self, take):
        if take.record and take.tracked_frames:
            webcam_take.last_take = take
        self.report(*webcam_take.take_report(take))
        return {'FINISHED'}


class _RunningTake:
    """Operators on the take in progress; they change no data, so they push no undo step (one
    would split the take's own)."""
    bl_options = {'REGISTER'}

    @classmethod
    def poll(cls, context):
        if webcam_take.running is None:
            cls.poll_message_set("No take is running: start Drive from Webcam first")
            return False
        return True


class EXCLONE_OT_stop_webcam(_RunningTake, bpy.types.Operator):
    """End the running take (everything it did stays, as one undo step)"""
    bl_idname = "exclone.stop_webcam"
    bl_label = "Stop"

    def execute(self, context):
        webcam_take.running.stop_requested = True
        return {'FINISHED'}


class EXCLONE_OT_calibrate_neutral(_RunningTake, bpy.types.Operator):
    """Restart the neutral-face calibration of the running take: hold a neutral face for a
    second"""
    bl_idname = "exclone.calibrate_neutral"
    bl_label = "Calibrate"

    def execute(self, context):
        take = webcam_take.running
        take.request_calibration()
        self.report({'INFO'}, f"Calibrating over the next {take.session.calibration_frames} "
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
        if not poll_no_take(cls):
            return False
        take = webcam_take.last_take
        try:
            usable = take is not None and take.avatar.name in bpy.data.objects
        except ReferenceError:
            usable = False
        if not usable:
            cls.poll_message_set("Record a take first (Refine works on the last recorded take)")
            return False
        return True

    @reporting
    def execute(self, context):
        take = webcam_take.last_take
        # nothing is written before the refinement succeeds
        timestamps, weights, names = take.session.refine_take(self.closeness, self.iterations)
        count, changes = take.rekey(timestamps, weights, names)
        change = f", mean change {np.mean(changes):.3f}" if changes else ""
        self.report({'INFO'}, f"Refined {count} frames of the take on '{take.avatar.name}'{change}")
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

    def _frames(self, context):
        if self.camera_frames:
            spec = webcam_take.source_spec(context, 'CAMERA', self.camera_index, "")
            with capture.open_source(spec) as source:
                frames = [source.read() for _ in range(10 * self.camera_frames)]
            return frames[::10]
        spec = webcam_take.source_spec(context, 'FOLDER', -1, self.directory)
        with capture.open_source(spec) as source:
            return list(source)

    @reporting
    def execute(self, context):
        # nothing is stored before the calibration succeeds
        frames = self._frames(context)
        camera, rms = calibrate_camera([frame.image for frame in frames], (self.columns, self.rows),
                                       names=[frame.name for frame in frames])
        webcam = context.scene.exclone.webcam
        height, width = frames[0].image.shape[:2]
        webcam.fx, webcam.fy, webcam.cx, webcam.cy = camera.fx, camera.fy, camera.cx, camera.cy
        webcam.calibration_width, webcam.calibration_height = width, height
        webcam.calibration_rms = rms
        webcam.calibrated = True
        self.report({'INFO'}, f"Camera calibrated from {len(frames)} images ({width} x {height}): "
                              f"fx {camera.fx:.1f}, fy {camera.fy:.1f}, centre ({camera.cx:.1f}, "
                              f"{camera.cy:.1f}), reprojection error {rms:.2f} px")
        return {'FINISHED'}


CLASSES = (EXCLONE_OT_drive_from_webcam, EXCLONE_OT_stop_webcam, EXCLONE_OT_calibrate_neutral,
           EXCLONE_OT_refine_take, EXCLONE_OT_calibrate_camera)
register, unregister = bpy.utils.register_classes_factory(CLASSES)
