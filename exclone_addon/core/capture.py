"""Frames from a camera, a video file or a folder of images, through OpenCV: what the live
tracker reads (docs/method.md §10).

Every source gives 8-bit BGR frames with a timestamp in seconds from the source's start: the wall
clock for a camera, the frame's place in the file for a video or a folder (so a file is tracked
the same however fast the machine is), and a name for messages about the frame.
"""
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from .errors import ExCloneError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
FOLDER_FRAME_RATE = 30.0


class CameraLost(ExCloneError):
    """The camera stopped delivering frames (unplugged, taken by another program)."""


@dataclass
class Frame:
    image: np.ndarray    # (H, W, 3) uint8 BGR
    timestamp: float     # seconds from the source's start
    index: int
    name: str            # what a message calls it: "image a.png", "frame 12 of clip.mp4"


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
        frame = Frame(_as_bgr(image), self._timestamp(), self._count, self._name())
        self._count += 1
        return frame

    def close(self):
        if self._capture is not None:
            self._capture.release()
            self._capture = None


class CameraSource(_CaptureSource):
    is_live = True

    def __init__(self, index):
        # Opening a missing camera makes OpenCV's backends log to stderr; their verdict is what counts.
        capture = cv2.VideoCapture(index)
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
        self._clock_start = time.monotonic()

    def _timestamp(self):
        return time.monotonic() - self._clock_start

    def _name(self):
        return f"frame {self._count} of camera {self.index}"

    def _ended(self):
        raise CameraLost(f"camera {self.index} stopped delivering frames")


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
                      f"image {Path(self.files[self._count]).name}")
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
