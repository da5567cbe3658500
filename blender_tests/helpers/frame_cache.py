"""Rendered frames cached on disk in the temp folder, shared by test runs: scripts/test.sh runs
its two environments at once, so one run renders a take while the other waits for it, and a
take is moved into place only when every frame is written (an interrupted render leaves none)."""
import contextlib
import fcntl
import shutil


@contextlib.contextmanager
def _locked(folder):
    folder.parent.mkdir(parents=True, exist_ok=True)
    with open(folder.with_name(folder.name + ".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield


def cached_frames(folder, count, render):
    """(paths of `count` PNG frames in `folder`, CPU seconds a frame took to render: 0 when
    they were cached). render(paths) writes the frames to the paths it is given."""
    paths = [folder / f"frame_{k:04d}.png" for k in range(count)]
    with _locked(folder):
        if all(path.is_file() for path in paths):
            return paths, 0.0
        staging = folder.with_name(folder.name + ".partial")
        shutil.rmtree(staging, ignore_errors=True)
        staging.mkdir()
        seconds = render([staging / path.name for path in paths])
        shutil.rmtree(folder, ignore_errors=True)
        staging.rename(folder)
    return paths, seconds
