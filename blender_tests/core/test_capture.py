"""core.capture: frames from a video file, a folder of images, a camera index; clear errors; a
camera read for its newest frame; core.tracking_worker: tracking on a worker thread."""
import collections
import threading
import time

import cv2
import numpy as np
import pytest

from exclone_addon.core.capture import (CameraLost, CameraSource, ImageSource, VideoSource,
                                        open_source)
from exclone_addon.core.errors import ExCloneError
from exclone_addon.core.tracking_worker import TrackingWorker, WorkerError


def numbered_frames(count, size=(64, 48)):
    """Frames whose mean grey level encodes their index (survives lossy video compression)."""
    return [np.full((size[1], size[0], 3), 20 + 20 * k, np.uint8) for k in range(count)]


def test_video_file_frames_in_order_with_timestamps(tmp_path):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (64, 48))
    assert writer.isOpened()
    for frame in numbered_frames(6):
        writer.write(frame)
    writer.release()
    with open_source(str(path)) as source:
        assert isinstance(source, VideoSource) and not source.is_live
        assert source.frame_rate == pytest.approx(25.0)
        assert source.frame_size == (64, 48)
        assert source.description == "video clip.avi (6 frames, 25 fps)"
        frames = list(source)
    assert [f.index for f in frames] == list(range(6))
    assert [f.name for f in frames] == [f"frame {k} of clip.avi" for k in range(6)]
    np.testing.assert_allclose([f.timestamp for f in frames], np.arange(6) / 25.0)
    np.testing.assert_allclose([f.image.mean() for f in frames], 20 + 20 * np.arange(6), atol=2)
    assert all(f.image.dtype == np.uint8 and f.image.shape == (48, 64, 3) for f in frames)


def test_folder_of_images_sorted_by_name(tmp_path):
    frames = numbered_frames(3)
    for k, name in enumerate(["b.png", "c.jpg", "a.bmp"]):
        cv2.imwrite(str(tmp_path / name), frames[k])
    (tmp_path / "notes.txt").write_text("not an image")
    with open_source(tmp_path, frame_rate=10) as source:
        assert isinstance(source, ImageSource)
        assert source.description == f"3 images in {tmp_path}"
        assert source.frame_rate == 10.0 and source.frame_size == (64, 48)
        read = list(source)
        assert source.read() is None
    # a.bmp (frame 2), b.png (frame 0), c.jpg (frame 1)
    np.testing.assert_allclose([f.image.mean() for f in read], [60, 20, 40], atol=2)
    np.testing.assert_allclose([f.timestamp for f in read], [0.0, 0.1, 0.2])
    assert [f.name for f in read] == ["image a.bmp", "image b.png", "image c.jpg"]
    with open_source(str(tmp_path / "b.png")) as single:
        assert single.description == "image b.png" and len(list(single)) == 1


def test_bad_sources_are_one_line_errors(tmp_path):
    with pytest.raises(ExCloneError, match="not found"):
        open_source(tmp_path / "missing.mp4")
    with pytest.raises(ExCloneError, match="holds no images"):
        open_source(tmp_path)
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"this is not a video" * 10)
    with pytest.raises(ExCloneError, match="not a readable video"):
        open_source(junk)
    broken = tmp_path / "images"
    broken.mkdir()
    cv2.imwrite(str(broken / "a.png"), numbered_frames(1)[0])
    (broken / "b.png").write_bytes(b"not a png")
    with open_source(broken) as source:
        source.read()
        with pytest.raises(ExCloneError, match="^image b.png is unreadable$"):
            source.read()
    # this machine has no camera; an index far beyond any real one is missing everywhere
    for spec in (63, "63"):
        with pytest.raises(ExCloneError, match="no camera at index 63"):
            open_source(spec)
    for spec in (tmp_path / "missing.mp4", tmp_path, junk, 63):
        with pytest.raises(ExCloneError) as info:
            open_source(spec)
        assert "\n" not in str(info.value)


class QueueingCamera:
    """What a camera's driver does, in time: a new frame every 1/fps seconds into a queue of
    `queue` frames (the oldest dropped when full); grab() takes the oldest queued frame (waiting
    for one), retrieve() decodes it. Each frame's grey level is its number modulo 200, so its
    age can be read off it. After `frames` frames the camera stops delivering (unplugged)."""

    def __init__(self, fps=30.0, queue=4, frames=10 ** 6):
        self.fps, self.queue_size, self.frames = fps, queue, frames
        self.start = time.monotonic()
        self.produced = 0            # frames moved into the queue so far
        self.queue = collections.deque()
        self.grabbed = None
        self.buffer_size_set = None

    def _fill(self):
        due = min(int((time.monotonic() - self.start) * self.fps) + 1, self.frames)
        while self.produced < due:
            self.queue.append(self.produced)
            if len(self.queue) > self.queue_size:
                self.queue.popleft()
            self.produced += 1

    def isOpened(self):
        return True

    def read(self):
        return self.grab(), self.retrieve()[1]

    def grab(self):
        deadline = time.monotonic() + 0.5
        while time.monotonic() < deadline:
            self._fill()
            if self.queue:
                self.grabbed = self.queue.popleft()
                return True
            time.sleep(0.002)
        return False

    def retrieve(self):
        return True, np.full((48, 64, 3), self.grabbed % 200, np.uint8)

    def latest(self):
        self._fill()
        return self.produced - 1

    def get(self, prop):
        return self.fps if prop == cv2.CAP_PROP_FPS else 0.0

    def set(self, prop, value):
        if prop == cv2.CAP_PROP_BUFFERSIZE:
            self.queue_size = int(value)
            self.buffer_size_set = value
        return True

    def release(self):
        pass


def test_a_camera_read_slowly_still_gives_its_newest_frame():
    """A tracker that needs 100 ms a frame reads a 30 fps camera: each frame it gets is at most
    about one frame old (read plainly from a 4-frame queue it would be up to 4 frames old)."""
    camera = QueueingCamera()
    source = CameraSource(0, capture=camera)
    try:
        assert camera.buffer_size_set == 1
        source.read()                            # the frame read on opening
        ages = []
        for _ in range(8):
            time.sleep(0.1)                      # tracking the previous frame
            frame = source.read()
            ages.append(camera.latest() % 200 - frame.image[0, 0, 0])
            assert time.monotonic() - frame.captured < 0.05
        assert max(ages) <= 1, ages
    finally:
        source.close()
    # the same camera read plainly, one read per tracked frame, from its 4-frame queue
    plain = QueueingCamera()
    stale = []
    for _ in range(8):
        time.sleep(0.1)
        _, image = plain.read()
        stale.append(plain.latest() % 200 - image[0, 0, 0])
    assert max(stale) >= 3, stale


def test_a_camera_that_stops_delivering_is_lost_in_one_line():
    source = CameraSource(0, capture=QueueingCamera(frames=3))
    try:
        source.read()
        with pytest.raises(CameraLost, match="^camera 0 stopped delivering frames$"):
            for _ in range(10):
                source.read()
    finally:
        source.close()


def test_worker_keeps_every_result_of_a_file_in_order_and_only_the_newest_of_a_camera():
    for live in (False, True):
        produced = iter(range(40))
        closed = threading.Event()
        worker = TrackingWorker(lambda: next(produced, None), live=live, on_exit=closed.set)
        if live:
            assert worker.wait(5.0)
        taken = []
        while not worker.finished:
            item = worker.next_item(timeout=0.05)
            if item is not None:
                taken.append(item)
        assert closed.is_set() and worker.wait(1.0)
        assert taken == ([39] if live else list(range(40)))


def test_worker_hands_its_error_over_and_stops_when_asked():
    def failing():
        raise ExCloneError("frame 3 of camera 0 is 1x1 pixels")
    worker = TrackingWorker(failing, live=True)
    item = worker.next_item(timeout=5.0)
    assert isinstance(item, WorkerError) and str(item.error) == "frame 3 of camera 0 is 1x1 pixels"
    assert worker.wait(1.0) and worker.finished

    closed = threading.Event()
    worker = TrackingWorker(lambda: time.sleep(0.01) or 1, live=True, on_exit=closed.set)
    worker.stop()
    assert worker.wait(1.0) and closed.is_set()
