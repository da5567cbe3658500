"""Tracking off the calling thread: a worker thread does a take's per-frame work (read a frame,
track it) and hands the results over; the caller (Blender's main thread, on a timer) only applies
them. OpenCV's networks and numpy release the GIL, so the tracking runs beside the user
interface instead of blocking it, calibration included.

A live source (a camera) keeps only the newest result: an older one not yet applied is stale.
A file keeps every result in order (a bounded queue the worker waits on), so a recorded take
keys every frame of the file whatever the timer does.
"""
import collections
import threading

# Results of a file waiting to be applied: the worker waits while this many are pending.
FILE_QUEUE = 4


class WorkerError:
    """What the worker raised, handed over to be raised where the result is applied."""

    def __init__(self, error):
        self.error = error


class TrackingWorker:
    """Runs track_next() in a loop on a daemon thread until it returns None (the source ended),
    raises (the error is the last item) or stop() is called; on_exit() (closing the source) then
    runs on the worker's own thread, so a source is never closed while it is being read."""

    def __init__(self, track_next, live, on_exit=None):
        self._track_next = track_next
        self._live = bool(live)
        self._on_exit = on_exit
        self._items = collections.deque()
        self._changed = threading.Condition()
        self._stopping = False
        self._done = False
        self.thread = threading.Thread(target=self._run, name="ExClone tracking", daemon=True)
        self.thread.start()

    def _run(self):
        try:
            while not self._stopping:
                item = self._track_next()
                if item is None:
                    break
                self._put(item)
        except Exception as exc:        # handed over: the caller ends the take with it
            self._put(WorkerError(exc))
        finally:
            try:
                if self._on_exit is not None:
                    self._on_exit()
            finally:
                with self._changed:
                    self._done = True
                    self._changed.notify_all()

    def _put(self, item):
        with self._changed:
            if self._live:
                self._items.clear()
            else:
                while len(self._items) >= FILE_QUEUE and not self._stopping:
                    self._changed.wait(0.1)
            self._items.append(item)
            self._changed.notify_all()

    def next_item(self, timeout=0.0):
        """The next result to apply (the newest for a live source, the oldest pending for a
        file), waiting up to `timeout` seconds; None when there is none yet."""
        with self._changed:
            if not self._items and timeout and not self._done:
                self._changed.wait(timeout)
            if not self._items:
                return None
            item = self._items.popleft()
            self._changed.notify_all()
            return item

    @property
    def finished(self):
        """The worker has stopped and every result was taken."""
        with self._changed:
            return self._done and not self._items

    def stop(self):
        """Asks the worker to stop after its current frame (it closes the source itself)."""
        with self._changed:
            self._stopping = True
            self._changed.notify_all()

    def wait(self, timeout=None):
        """Waits for the worker's thread to end; True when it did."""
        self.thread.join(timeout)
        return not self.thread.is_alive()
