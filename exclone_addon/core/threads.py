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

try:
    from threadpoolctl import threadpool_limits
except ImportError:
    threadpool_limits = None

# One BLAS thread was the fastest clone of the library onto a 10k-vertex target, idle and under
# load, on 2 cores (README, "Speed").
ENGINE_THREADS = 1


@contextlib.contextmanager
def engine_threads(limit=ENGINE_THREADS):
    """Within: BLAS and OpenMP pools limited to `limit` threads (no limit without threadpoolctl)."""
    if threadpool_limits is None:
        yield
        return
    with threadpool_limits(limits=limit):
        yield


def limited_threads(function):
    """`function` run within engine_threads()."""
    @functools.wraps(function)
    def limited(*args, **kwargs):
        with engine_threads():
            return function(*args, **kwargs)
    return limited
