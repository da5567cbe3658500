"""Drive from Webcam's take: the tracked face drives the avatar's shape keys (and a head rotation).

One frame's work is Take.step(): read a frame and track it (track_next: core.session, no bpy),
then apply the result (write the shape-key values and the head rotation, key them when
recording, show the camera preview). execute() (scripts, background Blender, where timers never
fire) and the tests call step() in a loop. In a window the modal operator runs track_next on a
worker thread (start_worker, core.tracking_worker) and its timer calls tick(), which only applies
the newest result: Blender's main thread spends about a millisecond a tick, calibration
included. step() and tick() never raise: an error (a bad frame, a lost camera) ends the take
with a one-line reason, and what it wrote so far stays.
"""
import collections
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import bpy
from bpy_extras import anim_utils

from ..core import capture
from ..core.errors import ExCloneError, user_message
from ..core.session import FaceTrackingSession
from ..core.tracking import Camera
from ..core.tracking_worker import TrackingWorker, WorkerError
from . import preferences
from .avatar_rig import avatar_rig, checked_avatar
from .camera_preview import preview_pixels, show_preview
from .head_motion import HeadTarget, head_holder

running = None        # the Take in progress in the UI (the Stop and Calibrate operators act on it)
last_take = None      # the last take that recorded keyframes (Refine Take rewrites them)
# How many of the latest frames' timings a take keeps (main-thread ms per applied frame, ms from
# a frame's capture to its shape keys written).
TIMINGS_KEPT = 10000


@dataclass
class TrackedFrame:
    """One frame's tracking, ready to apply on the main thread."""
    frame: capture.Frame
    result: object           # session.FrameResult
    preview: np.ndarray      # camera_preview.preview_pixels of the frame


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


class Take:
    """A take's state: the avatar, the frame source, the tracking session and what it wrote.

    step() does one frame; it returns False once the take is over (end of the file, stop
    requested, max_frames reached, or an error), with the reason in end_reason; `interrupted`
    says the take ended on an error."""

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
        self.interrupted = False
        self.stop_requested = False
        self.calibration_requested = False
        self.worker = None
        self.apply_ms = collections.deque(maxlen=TIMINGS_KEPT)
        self.latency_ms = collections.deque(maxlen=TIMINGS_KEPT)

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
        """One frame read, tracked and applied on this thread; False once the take is over.
        Never raises: an error ends the take with its one line in end_reason, and everything
        written before it stays."""
        return self._guarded(self._advance)

    def tick(self):
        """A timer tick while the worker runs: applies the newest tracked frame, if any; False
        once the take is over. Never raises, as step()."""
        return self._guarded(self._apply_newest)

    def _guarded(self, advance):
        try:
            return advance()
        except ReferenceError:      # the avatar was deleted or an undo replaced it
            return self._interrupt("the avatar was removed during the take")
        except Exception as exc:    # any other error (a bad frame, a lost camera) ends it too
            return self._interrupt(f"{user_message(exc)}: the take ended")

    def _interrupt(self, reason):
        self.end_reason, self.interrupted = reason, True
        return False

    def _over(self):
        """Why the take is over before the next frame, or None."""
        if self.stop_requested:
            return "stopped"
        if self.max_frames and self.frames_read >= self.max_frames:
            return f"{self.max_frames} frames read"
        return None

    def _advance(self):
        self.end_reason = self._over()
        if self.end_reason:
            return False
        tracked = self.track_next()
        if tracked is None:
            self.end_reason = "the source ended"
            return False
        self.apply(tracked)
        return True

    def request_calibration(self):
        """Recalibrate the neutral from the next frame on (the tracking side starts it, so a
        running worker is never raced)."""
        self.calibration_requested = True
        self.status = "calibrating: hold a neutral face"

    def track_next(self):
        """Reads and tracks one frame: a TrackedFrame, or None when the source ended. Touches no
        Blender data (the worker thread runs it)."""
        frame = self.source.read()
        if frame is None:
            return None
        if self.calibration_requested:
            self.calibration_requested = False
            self.session.calibrate()
        result = self.session.step(frame.image, frame.timestamp, frame.name)
        return TrackedFrame(frame, result,
                            preview_pixels(frame.image, result.landmarks if result.found else None))

    def apply(self, tracked):
        """Main thread: the tracked frame's weights and head rotation written (and keyed when
        recording), the preview shown; its timings recorded."""
        start = time.perf_counter()
        result = tracked.result
        self.frames_read += 1
        self.frames_with_face += bool(result.found)
        if not self.calibration_requested:
            self.status = result.status
        # Without a face the session repeats the last pose: it is held (and keyed) as it was.
        if result.weights is not None:
            self._write(result, tracked.frame.timestamp)
            self.latency_ms.append(1000 * (time.monotonic() - tracked.frame.captured))
        show_preview(tracked.preview)
        self.apply_ms.append(1000 * (time.perf_counter() - start))

    def start_worker(self):
        """From now on frames are read and tracked on a worker thread; tick() applies them."""
        self.worker = TrackingWorker(self.track_next, live=self.source.is_live,
                                     on_exit=self.source.close)

    def _apply_newest(self):
        self.end_reason = self._over()
        if self.end_reason:
            return False
        item = self.worker.next_item()
        if item is None:
            if self.worker.finished:
                self.end_reason = "the source ended"
                return False
            return True
        if isinstance(item, WorkerError):
            raise item.error
        self.apply(item)
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

    def rekey(self, timestamps, weights, names):
        """Rewrites the take's keyframes with refined weights (T, N) at its recorded timestamps;
        returns (frames rewritten, the changes |new - old| of the keyed values)."""
        frames = [self.tracked_frames.get(round(float(t), 6)) for t in timestamps]
        rows = [i for i, frame in enumerate(frames) if frame is not None]
        key = self.avatar.data.shape_keys
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
        self.scene.frame_set(self.scene.frame_current)
        return len(rows), changes

    def close(self):
        """Ends the take's reading: a running worker is stopped and closes the source itself
        once its current frame is done (the main thread never waits for a calibration)."""
        if self.worker is not None:
            self.worker.stop()
        else:
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
    if take.interrupted:
        return {'WARNING'}, f"{take.end_reason}; {text} (what was recorded is kept)"
    return {'INFO'}, f"{text} ({take.end_reason}; last status: {take.status})"


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


def start_take(context, *, source_type, camera_index=-1, filepath="", record=False, key_set='ALL',
               head_kind='NONE', armature="", bone="", max_frames=0, use_calibration=True,
               use_appearance=True, progress=None):
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
        session = FaceTrackingSession(
            avatar=rig, camera=camera, calibration_frames=max(1, round(source.frame_rate or 30)),
            appearance=use_appearance)
    except BaseException:
        source.close()
        raise
    if holder is not None:
        context.view_layer.update()         # world matrices of objects moved by scripts
    head = HeadTarget(*holder) if holder is not None else None
    return Take(context.scene, avatar, rig.names, source, session, record=record, head=head,
                max_frames=max_frames)
