"""What the command lines (batch_clone.py, track_video.py) share: an argument parser whose errors
are ExCloneErrors, number arguments that must be finite, output paths checked before the long
work, outputs written under temporary names and moved into place together, and `run_main`:
exit code 0, or 1 after one line `prog: error: ...` on stderr.
"""
import argparse
import contextlib
import math
import os
import signal
import sys
from pathlib import Path

from exclone_addon.core.errors import ExCloneError, user_message


class Parser(argparse.ArgumentParser):
    """argparse with its usage errors raised as ExCloneError, so run_main prints them as one line."""

    def error(self, message):
        raise ExCloneError(message)


def number(kind=float, *, positive=False, at_least=None):
    """An argparse `type`: a finite int or float (inf and nan are refused), optionally > 0 or
    >= at_least. argparse prefixes its messages with the option: "argument --fps: ..."."""
    what = "a whole number" if kind is int else "a number"

    def parse(text):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {what}, got '{text}'") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"must be a finite number, got '{text}'")
        if positive and value <= 0:
            raise argparse.ArgumentTypeError(f"must be positive, got {value:g}")
        if at_least is not None and value < at_least:
            raise argparse.ArgumentTypeError(f"must be at least {at_least}, got {value:g}")
        return value

    parse.__name__ = kind.__name__
    return parse


def _nearest_existing(path):
    return next(p for p in (path, *path.parents) if p.exists() or p.is_symlink())


def check_folder_writable(folder, shown=None):
    """ExCloneError now, before any long work, if files cannot be made in `folder` (which may
    not exist yet): a part of it is a file, or its nearest existing folder is not writable (a
    read-only disk or no permission). `shown`: the output named in the message."""
    folder = Path(folder).absolute()
    shown = shown or folder
    existing = _nearest_existing(folder)
    if not existing.is_dir():
        raise ExCloneError(f"cannot write {shown}: {existing} is a file, not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ExCloneError(f"cannot write {shown}: the folder {existing} is not writable")


def check_output_writable(path):
    """ExCloneError now, before any long work, if the output file `path` cannot be written."""
    path = Path(path)
    if path.is_dir():
        raise ExCloneError(f"output {path} is a folder")
    check_folder_writable(path.parent, shown=path)


class Outputs:
    """A run's output files, each written under a temporary name next to its final one and all
    moved into place by commit(): a run that fails leaves no half-written output and replaces no
    earlier one. Use as a context manager: leaving it by an exception removes the temporary files
    and the folders made for them."""

    def __init__(self):
        self._staged = []     # (temporary path, final path)
        self._made = []       # folders made for the outputs, outermost first

    def _make_folder(self, folder):
        missing = [p for p in (folder, *folder.parents) if not p.exists()]
        for path in reversed(missing):
            path.mkdir()
            self._made.append(path)

    def write(self, final, write):
        """Call write(temporary path) for the output `final`; a failure (full disk, read-only
        folder) is an ExCloneError naming `final`."""
        final = Path(final)
        temporary = final.with_name(f".{final.stem}.partial{final.suffix}")
        self._staged.append((temporary, final))
        try:
            self._make_folder(final.parent)
            write(temporary)
        except OSError as exc:
            raise ExCloneError(f"cannot write {final}: {exc.strerror or exc}") from exc
        if not temporary.is_file():
            raise ExCloneError(f"cannot write {final}: nothing was written")

    def commit(self):
        """Move every output into place; returns the final paths."""
        moved = []
        for temporary, final in self._staged:
            try:
                os.replace(temporary, final)
            except OSError as exc:
                written = ", ".join(map(str, moved)) or "nothing"
                raise ExCloneError(f"cannot write {final}: {exc.strerror or exc} (written: "
                                   f"{written})") from exc
            moved.append(final)
        self._staged = []
        return moved

    def discard(self):
        for temporary, _ in self._staged:
            temporary.unlink(missing_ok=True)
        self._staged = []
        for folder in reversed(self._made):
            with contextlib.suppress(OSError):   # not empty: something else was put there
                folder.rmdir()

    def __enter__(self):
        return self

    def __exit__(self, error_type, *_):
        self.discard()    # after commit() only the folders that are still empty, i.e. none


@contextlib.contextmanager
def stderr_to_stdout():
    """Send everything written to stderr meanwhile (Blender's and OpenCV's own messages, e.g. EGL
    warnings while rendering or a missing camera) to stdout, so that stderr carries only our
    one-line error."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(2)
    os.dup2(1, 2)
    try:
        yield
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os.dup2(saved, 2)
        os.close(saved)


def _stop_as_interrupted(*_):
    raise KeyboardInterrupt


def run_main(prog, work):
    """Run work() and return the exit code: 0, or 1 after one line `prog: error: ...` on stderr.
    SIGTERM (a batch or a render farm stopping this run) ends it as Ctrl-C does: no output is
    left half-written."""
    signal.signal(signal.SIGTERM, _stop_as_interrupted)
    try:
        with stderr_to_stdout():
            work()
        return 0
    except (ExCloneError, OSError) as exc:
        message = str(exc)
    except KeyboardInterrupt:
        message = "interrupted"
    except Exception as exc:  # one line for the user; EXCLONE_DEBUG=1 shows the traceback
        if os.environ.get("EXCLONE_DEBUG"):
            raise
        message = f"{user_message(exc)}; run with EXCLONE_DEBUG=1 for the traceback"
    print(f"{prog}: error: " + " ".join(message.split()), file=sys.stderr, flush=True)
    return 1
