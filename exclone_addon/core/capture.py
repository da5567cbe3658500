"""Frames from a camera, a video file or a folder of images, through OpenCV: what the live
tracker reads (docs/method.md §10).

Every source gives 8-bit BGR frames with a timestamp in seconds from the source's start: the wall
clock for a camera, the frame's place in the file for a video or a folder (so a file is tracked
the same however fast the machine is), and a name for messages about the frame.

A camera is read for its newest frame: its driver keeps a queue of frames (OpenCV's default is
four; a 1080p MJPEG camera read once per tracked frame then delivers frames about 200 ms old),
so the queue is shortened to one where the backend allows and a reader thread grabs every frame
as it arrives, decoding only the one asked for.
"""
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from .errors import ExCloneError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
FOLDER_FRAME_RATE = 30.0
# A camera that delivers no frame for this long is lost.
CAMERA_TIMEOUT_S = 2.0


class CameraLost(ExCloneError):
    """The camera stopped delivering frames (unplugged, taken by another program)."""


@dataclass
class Frame:
    image: np.ndarray    # (H, W, 3) uint8 BGR
    timestamp: float     # seconds from the source's start
    index: int
    name: str            # what a message calls it: "image a.png", "frame 12 of clip.mp4"
    captured: float = 0.0    # time.monotonic() when it was grabbed (camera) or read (file)


class FrameSource:
    """Base of the three sources; a context manager that closes the source."""
    description = ""
    is_live = False
    frame_rate = None
    frame_size = (0, 0)

    def read(self):
        raise NotImplementedError

    def close(self):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __iter__(self):
        while (frame := self.read()) is not None:
            yield frame


class _CaptureSource(FrameSource):
    """An OpenCV VideoCapture whose first frame was read on opening (so a source that opens but
    delivers nothing fails before the take starts)."""

    def _start(self, capture, first_image):
        self._capture, self._pending, self._count = capture, first_image, 0
        self.frame_size = (first_image.shape[1], first_image.shape[0])

    def _timestamp(self):
        raise NotImplementedError

    def _name(self):
        """What the frame about to be returned is called in a message."""
        raise NotImplementedError

    def _ended(self):
        """What read() gives when the capture delivers no more frames."""
        raise NotImplementedError

    def read(self):
        if self._capture is None:
            return None
        if self._pending is not None:
            image, self._pending = self._pending, None
        else:
            ok, image = self._capture.read()
            if not ok or image is None:
                return self._ended()
        frame = Frame(_as_bgr(image), self._timestamp(), self._count, self._name(), time.monotonic())
        self._count += 1
        return frame

    def close(self):
        if self._capture is not None:
            self._capture.release()
            self._capture = None


class NewestFrameReader:
    """Grabs a capture's frames on its own thread as they arrive (so the driver's queue never
    fills with old ones) and decodes only the one asked for: read() gives the first frame
    grabbed after the call, with its grab time. The capture is used by this thread alone."""

    def __init__(self, capture, timeout=CAMERA_TIMEOUT_S):
        self._capture = capture
        self._timeout = timeout
        self._wanted = threading.Event()
        self._delivered = threading.Event()
        self._frame = None          # (image, grab time) or None (the capture failed)
        self._stopping = False
        self._thread = threading.Thread(target=self._run, name="ExClone camera", daemon=True)
        self._thread.start()

    def _run(self):
        last_frame = time.monotonic()
        while not self._stopping:
            if not self._capture.grab():
                if time.monotonic() - last_frame > self._timeout:
                    break
                time.sleep(0.005)
                continue
            last_frame = time.monotonic()
            if self._wanted.is_set():
                ok, image = self._capture.retrieve()
                self._frame = (image, last_frame) if ok and image is not None else None
                self._wanted.clear()
                self._delivered.set()
        self._frame = None
        self._delivered.set()       # a waiting read() learns that no frame will come

    def read(self):
        """(BGR image, time.monotonic() of its grab), or None when the capture delivers nothing
        within the timeout."""
        if not self._thread.is_alive():
            return None
        self._delivered.clear()
        self._wanted.set()
        if not self._delivered.wait(self._timeout):
            return None
        return self._frame

    def close(self):
        """Stops grabbing; True when the thread ended (the capture may then be released)."""
        self._stopping = True
        self._thread.join(self._timeout + 1.0)
        return not self._thread.is_alive()


class CameraSource(_CaptureSource):
    """A camera by index, read for its newest frame (NewestFrameReader). capture: an opened
    VideoCapture-like object to read instead of opening the index (a paced clip in tests)."""
    is_live = True

    def __init__(self, index, capture=None):
        # Opening a missing camera makes OpenCV's backends log to stderr; their verdict is what counts.
        capture = cv2.VideoCapture(index) if capture is None else capture
        if not capture.isOpened():
            capture.release()
            raise ExCloneError(f"no camera at index {index}")
        ok, image = capture.read()
        if not ok or image is None:
            capture.release()
            raise ExCloneError(f"camera {index} opened but delivers no frames")
        self._start(capture, image)
        self.index = index
        self.description = f"camera {index}"
        fps = capture.get(cv2.CAP_PROP_FPS)
        self.frame_rate = float(fps) if fps and fps > 0 else None
        # one frame in the driver's queue where the backend supports it (not all do)
        capture.set(cv2.CAP_PROP_BUFFERSIZE, 1)
        self._clock_start = time.monotonic()
        self._reader = NewestFrameReader(capture)

    def read(self):
        if self._capture is None:
            return None
        if self._pending is not None:
            image, self._pending = self._pending, None
            grabbed = time.monotonic()
        else:
            newest = self._reader.read()
            if newest is None:
                raise CameraLost(f"camera {self.index} stopped delivering frames")
            image, grabbed = newest
        frame = Frame(_as_bgr(image), grabbed - self._clock_start, self._count,
                      f"frame {self._count} of camera {self.index}", grabbed)
        self._count += 1
        return frame

    def close(self):
        if self._capture is not None:
            if self._reader.close():
                self._capture.release()
            self._capture = None


class VideoSource(_CaptureSource):
    def __init__(self, path):
        capture = cv2.VideoCapture(str(path))
        ok, image = capture.read() if capture.isOpened() else (False, None)
        if not ok or image is None:
            capture.release()
            raise ExCloneError(f"{path} is not a readable video")
        self._start(capture, image)
        fps = capture.get(cv2.CAP_PROP_FPS)
        self.frame_rate = float(fps) if fps and fps > 0 else FOLDER_FRAME_RATE
        self.frame_count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        self.file_name = Path(path).name
        self.description = (f"video {Path(path).name} ({self.frame_count} frames, "
                            f"{self.frame_rate:g} fps)")

    def _timestamp(self):
        # from the frame's place: container timestamps are often missing or zero
        return self._count / self.frame_rate

    def _name(self):
        return f"frame {self._count} of {self.file_name}"

    def _ended(self):
        return None


class ImageSource(FrameSource):
    """Image files in the given order (a folder's sorted by name, or one image); each may have
    its own size."""

    def __init__(self, files, description, frame_rate=None):
        self.files = list(files)
        self.frame_rate = float(frame_rate) if frame_rate else FOLDER_FRAME_RATE
        first = self._load(self.files[0])
        self._pending = first
        self.frame_size = (first.shape[1], first.shape[0])
        self.description = description
        self._count = 0

    @staticmethod
    def _load(file):
        image = cv2.imread(str(file), cv2.IMREAD_COLOR)
        if image is None:
            raise ExCloneError(f"image {Path(file).name} is unreadable")
        return image

    def read(self):
        if self._count >= len(self.files):
            return None
        if self._pending is not None:
            image, self._pending = self._pending, None
        else:
            image = self._load(self.files[self._count])
        frame = Frame(image, self._count / self.frame_rate, self._count,
                      f"image {Path(self.files[self._count]).name}", time.monotonic())
        self._count += 1
        return frame


def _as_bgr(image):
    """Cameras may deliver grey or BGRA frames; the tracker wants 3 channels."""
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    return image


def open_source(spec, frame_rate=None):
    """A FrameSource for a camera index (int or a string of digits), a video file or a folder of
    images. frame_rate: the rate given to a folder's images (default 30). Raises ExCloneError
    with one line that says what is wrong."""
    if isinstance(spec, (int, np.integer)) or (isinstance(spec, str) and spec.strip().isdigit()):
        return CameraSource(int(spec))
    path = Path(spec)
    if not path.exists():
        raise ExCloneError(f"not found: {path}")
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise ExCloneError(f"folder {path} holds no images ({' '.join(IMAGE_SUFFIXES)})")
        return ImageSource(files, f"{len(files)} images in {path}", frame_rate)
    if path.suffix.lower() in IMAGE_SUFFIXES:
        return ImageSource([path], f"image {path.name}", frame_rate)
    return VideoSource(path)
