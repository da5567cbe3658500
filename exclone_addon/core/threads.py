"""How many threads numpy's and scipy's BLAS (and any OpenMP pool) use while the engine works.

By default OpenBLAS runs every matrix operation on one thread per core. The engine's are many
small operations, and a pool thread that waits for a core another process holds stalls the
whole operation: with other work on the machine (Blender's own threads, a second clone, a
batch) the default pool made a clone several times slower than one thread, and idle it was no
faster (the figures are in the README). `limited_threads` decorates the engine's entry points
(core.cloning) so that they run with ENGINE_THREADS; the pools are as they were afterwards.

threadpoolctl does the limiting. Without it (an install that lacks the package) nothing is
limited and the engine runs as before, only slower on a busy machine.
"""
import contextlib
import functools

import cv2

try:
    from threadpoolctl import ThreadpoolController, threadpool_limits
except ImportError:
    ThreadpoolController = threadpool_limits = None

# One BLAS thread was the fastest clone of the library onto a 10k-vertex target, idle and under
# load, on 2 cores (docs/measurements.md, "BLAS threads").
ENGINE_THREADS = 1


@contextlib.contextmanager
def engine_threads(limit=ENGINE_THREADS):
    """Within: BLAS and OpenMP pools limited to `limit` threads (no limit without threadpoolctl)."""
    if threadpool_limits is None:
        yield
        return
    with threadpool_limits(limits=limit):
        yield


@functools.lru_cache(maxsize=1)
def _pools():
    """The process's thread pools, inspected once (an inspection costs about 2 ms)."""
    return ThreadpoolController()


@contextlib.contextmanager
def step_threads(limit=ENGINE_THREADS):
    """engine_threads for a live-tracking frame (core.session): the pools found at the first
    call, limited without inspecting them again (0.01 ms instead of 2 ms a frame). The shape
    fit's and the weight solve's small matrices cost 2.3 and 2.9 times the CPU on OpenBLAS's
    default pool of 2 threads (measured by scripts/bench_track.py). OpenCV's own pool is
    limited too: the step runs the iris model on a thread of its own beside the fit, and
    OpenCV's threads beside them made the step slower (14.0 ms against 13.2 median, 24 CPU ms
    against 19, scripts/bench_track.py on 2 cores)."""
    with opencv_threads(limit):
        if ThreadpoolController is None:
            yield
            return
        with _pools().limit(limits=limit):
            yield


@contextlib.contextmanager
def opencv_threads(count):
    """Within: OpenCV's own parallel loops (its networks' layers among them) on `count` threads
    (a setting of the whole process); as before afterwards."""
    before = cv2.getNumThreads()
    cv2.setNumThreads(count)
    try:
        yield
    finally:
        cv2.setNumThreads(before)


def limited_threads(function):
    """`function` run within engine_threads()."""
    @functools.wraps(function)
    def limited(*args, **kwargs):
        with engine_threads():
            return function(*args, **kwargs)
    return limited
