"""core.threads: the engine's entry points run with a limited BLAS pool, restored afterwards."""
import numpy as np  # noqa: F401  (loads OpenBLAS, whose pool is measured)
import pytest

from exclone_addon.core import cloning, threads

threadpoolctl = pytest.importorskip("threadpoolctl")


def blas_threads():
    return [pool["num_threads"] for pool in threadpoolctl.threadpool_info()
            if pool["user_api"] == "blas"]


def test_engine_entry_points_run_with_the_limit_and_restore_the_pools():
    before = blas_threads()
    assert before
    seen = []
    threads.limited_threads(lambda: seen.append(blas_threads()))()
    assert seen == [[threads.ENGINE_THREADS] * len(before)]
    assert blas_threads() == before
    for entry in (cloning.fit_faces, cloning.fit_registered, cloning.transfer_expressions,
                  cloning.clone_expressions):
        assert entry.__wrapped__.__module__ == cloning.__name__, entry.__name__


def test_without_threadpoolctl_nothing_is_limited(monkeypatch):
    monkeypatch.setattr(threads, "threadpool_limits", None)
    before = blas_threads()
    with threads.engine_threads():
        assert blas_threads() == before
