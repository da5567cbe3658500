"""The part of batch_clone.py's run on one target that needs no Blender: the source read and cut
to --shapes, the face found on an OBJ target, the clone of the expressions onto the face's head
and their measures.

batch_clone.py runs `cloned` in its own process when Blender reads the source. When the source
is plain files (a folder of OBJs, the bundled library) on Linux, it loads the engine and forks
(CloneProcess: the copy shares what is loaded). For an OBJ target without --landmarks, the copy
makes the object Blender will make of the target (target_part) and finds the face on it while
batch_clone reads the source and sends it over; the copy then clones, while batch_clone loads
Blender (`import bpy` and its own modules, ~0.7 CPU s) and reads the target. batch_clone uses
that face and clone only if Blender's object is the copy's to the bit; otherwise it finds the
face itself and sends it to be cloned (as it does with --landmarks).

The processes exchange pickled messages through a multiprocessing Pipe: batch_clone sends the
source (None if it could not read it), then (face, landmarks), face None for the copy's own,
verified. The copy sends, with guess, ("face", Part or None, face or None); ("progress",
fraction, message)... while it clones; ("cloned", Cloned) when asked; ("error", exception) if
it failed. Each process reads what it is sent on a thread of the copy (Outbox, Inbox), so that
neither waits for the other to read a large message: batch_clone's own process, which loads
Blender meanwhile, runs no thread (a library Blender loads can wait for the GIL while holding
the dynamic loader's lock: a deadlock).
"""
import ctypes
import multiprocessing
import os
import pickle
import queue
import signal
import sys
import threading
import time
import traceback
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from exclone_addon.blender import plain_files
from exclone_addon.core import character, data
from exclone_addon.core.cloning import CloneSettings, clone_expressions
from exclone_addon.core.errors import ExCloneError, user_message
from exclone_addon.core.expression_measures import measure_clone
from exclone_addon.core.mesh import PolyMesh, read_obj

PR_SET_PDEATHSIG = 1      # Linux's prctl option: a signal for this process when its parent ends


@dataclass
class Cloned:
    result: object        # core.cloning.CloneResult (deltas: the head's, world space)
    measures: list        # core.expression_measures.measure_clone's
    landmarks: dict       # {name: (3,) world point} of the result's target landmarks
    timings: dict         # seconds: clone_<phase>, clone_total, measures


def selected_shapes(source, shapes):
    """The source restricted to the --shapes list (None: all of it)."""
    if shapes is None:
        return source
    wanted = list(dict.fromkeys(name.strip() for name in shapes.split(",") if name.strip()))
    if not wanted:
        raise ExCloneError("--shapes names no expression")
    unknown = [name for name in wanted if name not in source.names]
    if unknown:
        raise ExCloneError(f"unknown expression(s) {', '.join(unknown)}; available: "
                           f"{', '.join(source.names[:6])}, ... ({len(source.names)} in all)")
    return source.subset(wanted)


def cloned(source, face, landmarks, progress):
    """The source's expressions (core.library.ExpressionLibrary) cloned onto the face's head
    (core.character.CharacterFace, world space; landmarks: pairs in its head's numbering or
    None), and measured beside the source so that the stretch is counted beyond the source's
    own (excess_stretch)."""
    clock = time.perf_counter()
    result = clone_expressions(source.mesh, source.deltas, source.names, face.head.mesh,
                               landmarks=landmarks, source_landmarks=source.automatic_landmarks,
                               source_modes=source.shape_modes,
                               settings=CloneSettings(), progress=progress,
                               face_guide=face.guide, fixed_vertices=face.head.fixed,
                               shared_vertices=character.shared_vertices(source, face))
    timings = {f"clone_{phase}": seconds for phase, seconds in result.timings.items()}
    timings["clone_total"] = time.perf_counter() - clock
    clock = time.perf_counter()
    measures = measure_clone(face.head.mesh, result, source=source.mesh,
                             source_deltas=source.deltas)
    points = dict(zip(result.landmark_names, face.world_points(
        face.head.mesh.vertices[np.asarray(result.target_landmarks)])))
    timings["measures"] = time.perf_counter() - clock
    return Cloned(result, measures, points, timings)


def target_part(spec):
    """The core.character.Part of the object Blender makes of an OBJ target (files.load_target:
    named after the file, its coordinates stored as float32, turned by the float32 matrix of
    plain_files.OBJ_ROTATION), or None if the target is no OBJ or cannot be read (Blender's
    reading then says why)."""
    path = data.DEMO_HEAD_FILE if spec is None else plain_files.split_spec(spec)[0]
    if path.suffix.lower() != ".obj" or not path.is_file():
        return None
    try:
        mesh = plain_files.checked(read_obj(path), f"target {path}")
    except (ExCloneError, OSError):
        return None
    turn = Rotation.from_euler("xyz", np.float32(plain_files.OBJ_ROTATION)).as_matrix()
    turn = turn.astype(np.float32).astype(np.float64)
    # + 0.0: the matrix's translation, as blender/character.to_world adds it (no -0.0)
    vertices = mesh.vertices.astype(np.float32).astype(np.float64) @ turn.T + 0.0
    return character.Part(path.stem, PolyMesh(vertices, mesh.loop_totals, mesh.loop_vertices))


def same_part(part, other):
    """True if two Parts are one object's, to the bit."""
    return part.name == other.name and all(
        ours.dtype == theirs.dtype and ours.shape == theirs.shape
        and ours.tobytes() == theirs.tobytes()
        for ours, theirs in ((part.mesh.vertices, other.mesh.vertices),
                             (part.mesh.loop_totals, other.mesh.loop_totals),
                             (part.mesh.loop_vertices, other.mesh.loop_vertices)))


# Set (to anything) in a process that must not fork: a batch running several targets at a time
# shares the cores between them, so a copy would only add its memory (~100 MiB).
ONE_PROCESS = "EXCLONE_ONE_PROCESS"


def can_fork():
    """True where CloneProcess runs: Linux, unless ONE_PROCESS is set. Windows cannot fork, and
    on macOS a forked child may not use what its parent loaded of the system's frameworks
    (numpy's Accelerate)."""
    return sys.platform.startswith("linux") and ONE_PROCESS not in os.environ


class CloneProcess:
    """A fork of this process that, with guess, finds the face on the object Blender will make
    of the target spec and clones at once; meanwhile this process reads the source spec
    (plain files: blender/plain_files.py) cut to `shapes` and sends it. Then `source`, `face`
    and `clone` as batch_clone needs them. Started before Blender is loaded. A context manager:
    on leaving, the process is stopped if it still runs."""

    def __init__(self, source_spec, shapes, target_spec, guess):
        self.started = time.perf_counter()
        context = multiprocessing.get_context("fork")
        self.connection, theirs = context.Pipe()
        self.process = context.Process(target=serve, daemon=True,
                                       args=(theirs, os.getpid(), target_spec, guess))
        self.process.start()
        theirs.close()
        self.guess = guess
        self.verified = False       # the face found there is the one batch_clone uses
        clock = time.perf_counter()
        try:
            source = selected_shapes(plain_files.load_source(source_spec), shapes)
            self._source = (source, time.perf_counter() - clock)
        except Exception as exc:    # raised when batch_clone asks for the source
            self._source, source = exc, None
        try:
            self.connection.send(source)    # read at once there (Inbox)
        except OSError:                     # it has ended: _receive says how
            pass

    def _receive(self):
        """The next message from the process: (kind, values); the error it sent raised here."""
        try:
            kind, *values = self.connection.recv()
        except EOFError:
            self.process.join()
            raise RuntimeError("the clone's process ended unexpectedly (exit code "
                               f"{self.process.exitcode})") from None
        if kind == "error":
            raise values[0]
        return kind, values

    def source(self):
        """(the source as an ExpressionLibrary, seconds it took to read); the error reading it
        raised here."""
        if isinstance(self._source, Exception):
            raise self._source
        return self._source

    def face(self, parts, find):
        """The CharacterFace on the target's parts (Blender's): the one found in the process if
        it found it on these parts to the bit, else find(parts)'s. A bad source's error first,
        as if the source were read first."""
        self.source()
        if self.guess:
            part, face = self._receive()[1]
            self.verified = part is not None and len(parts) == 1 and same_part(part, parts[0])
            if self.verified:
                return face
        return find(parts)

    def clone(self, face, landmarks, progress):
        """`cloned` in the process (Cloned): the one it made at once if its face is `face` (and
        no landmarks), else made now. progress(fraction, message) is called here."""
        self.connection.send((None if self.verified and landmarks is None else face, landmarks))
        while True:
            kind, values = self._receive()
            if kind == "cloned":
                return values[0]
            progress(*values)

    def __enter__(self):
        return self

    def __exit__(self, *_):
        if self.process.is_alive():
            self.process.kill()
        self.process.join()
        self.connection.close()


class Inbox(threading.Thread):
    """The next message on a connection, received on a thread (`message` once joined)."""

    def __init__(self, connection):
        super().__init__(daemon=True)
        self.connection, self.message = connection, None
        self.start()

    def run(self):
        self.message = self.connection.recv()


class Outbox(threading.Thread):
    """Messages sent in order on a thread, so that the sender never waits for the reader."""

    def __init__(self, connection):
        super().__init__(daemon=True)
        self.connection, self.queue = connection, queue.Queue()
        self.start()

    def send(self, *message):
        self.queue.put(message)

    def run(self):
        try:
            while (message := self.queue.get()) is not None:
                self.connection.send(message)
        except OSError:     # batch_clone has stopped reading: it is ending, so does this process
            pass

    def close(self):
        """Wait until everything is sent."""
        self.queue.put(None)
        self.join()


def serve(connection, parent, target_spec, guess):
    """The forked process (the module's docstring); parent: batch_clone's process id."""
    # killed when batch_clone's process ends, however it ends (stopped while loading Blender,
    # before it can stop this one)
    ctypes.CDLL(None).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:
        return
    os.dup2(1, 2)   # as batch_clone's own run does (exclone_cli): stderr is for its error line
    inbox, outbox = Inbox(connection), Outbox(connection)
    try:
        guessed = part = face = None
        if guess:
            part = target_part(target_spec)
            if part is not None:
                try:
                    face = character.found_or_whole([part])
                except Exception:   # batch_clone finds it on its own object, or says why not
                    part = None
            outbox.send("face", part, face)
        inbox.join()
        source = inbox.message
        if source is None:          # batch_clone could not read it, and says why
            return
        if face is not None:
            guessed = cloned(source, face, None,
                             lambda fraction, message: outbox.send("progress", fraction, message))
        face, landmarks = connection.recv()
        if face is not None:
            guessed = cloned(source, face, landmarks,
                             lambda fraction, message: outbox.send("progress", fraction, message))
        outbox.send("cloned", guessed)
    except (EOFError, BrokenPipeError, KeyboardInterrupt):  # batch_clone stopped: so does this
        return
    except Exception as exc:  # batch_clone reports it
        if os.environ.get("EXCLONE_DEBUG"):
            traceback.print_exc()
        try:
            pickle.dumps(exc)
        except (pickle.PicklingError, TypeError, AttributeError):
            exc = RuntimeError(user_message(exc))
        outbox.send("error", exc)
    finally:
        outbox.close()
