"""What the command-line scripts share: stderr keeps only our one-line error; exit codes."""
import contextlib
import os
import sys

from .core.errors import ExCloneError


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


def run_main(prog, work):
    """Run work() and return the exit code: 0, or 1 after one line `prog: error: ...` on stderr."""
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
        message = (f"internal error ({type(exc).__name__}: {exc}); "
                   "run with EXCLONE_DEBUG=1 for the traceback")
    print(f"{prog}: error: " + " ".join(message.split()), file=sys.stderr, flush=True)
    return 1
