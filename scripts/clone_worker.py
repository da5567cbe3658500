"""The part of batch_clone.py's run on one target that needs no Blender: the source read and cut
to --shapes, the face found on an OBJ target, the clone of the expressions onto the face's head
and their measures.

batch_clone.py runs `cloned` in its own process when Blender reads the source. When the source
is plain files (a folder of OBJs, the bundled library) on Linux, it loads the engine, forks
(CloneProcess: the copy shares what is loaded) and loads Blender (`import bpy` and its own
modules, ~0.7 CPU s) while the copy, on the other core, reads the source and, for an OBJ target
without --landmarks, makes the object Blender will make of the target (target_part), finds the
face on it and clones. batch_clone reads the target in Blender as before and uses that face and
clone only if its object is that one to the bit; otherwise it finds the face itself and sends
it to be cloned.

The processes exchange pickled messages through a multiprocessing Pipe. batch_clone's is
(face, landmarks), face None for the face found in the copy, verified. The copy's are
("source", library, seconds); with guess, ("face", Part or None, face or None); ("progress",
fraction, message)... while it clones; ("cloned", Cloned) when asked. ("error", exception)
stands for whichever failed.
"""
import ctypes
import multiprocessing
import os
import pickle
import signal
import sys
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


def can_fork():
    """True where CloneProcess runs: Linux. Windows cannot fork, and on macOS a forked child
    may not use what its parent loaded of the system's frameworks (numpy's Accelerate)."""
    return sys.platform.startswith("linux")


class CloneProcess:
    """A fork of this process reading the source spec (plain files: blender/plain_files.py)
    cut to `shapes` at once and, with guess, finding the face on the target spec and cloning;
    then `source`, `face` and `clone` as batch_clone needs them. Started before Blender is
    loaded. A context manager: on leaving, the process is stopped if it still runs."""

    def __init__(self, source_spec, shapes, target_spec, guess):
        context = multiprocessing.get_context("fork")
        self.connection, theirs = context.Pipe()
        self.process = context.Process(target=serve, daemon=True,
                                       args=(theirs, os.getpid(), source_spec, shapes,
                                             target_spec, guess))
        self.process.start()
        theirs.close()
        self.guess = guess
        self.verified = False       # the face found there is the one batch_clone uses
        self._source = None         # source's outcome: (library, seconds) or the exception

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
        raised here (each time asked)."""
        if self._source is None:
            try:
                self._source = tuple(self._receive()[1])
            except Exception as exc:
                self._source = exc
        if isinstance(self._source, Exception):
            raise self._source
        return self._source

    def face(self, parts, find):
        """The CharacterFace on the target's parts (Blender's): the one found in the process if
        it found it on these parts, else find(parts)'s. A bad source's error first, as if the
        source were read first."""
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


def serve(connection, parent, source_spec, shapes, target_spec, guess):
    """The forked process (the module's docstring); parent: batch_clone's process id."""
    # killed when batch_clone's process ends, however it ends (stopped while loading Blender,
    # before it can stop this one)
    ctypes.CDLL(None).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:
        return
    os.dup2(1, 2)   # as batch_clone's own run does (exclone_cli): stderr is for its error line

    def send(*message):
        connection.send(message)

    def progress(fraction, message):
        send("progress", fraction, message)

    try:
        clock = time.perf_counter()
        source = selected_shapes(plain_files.load_source(source_spec), shapes)
        send("source", source, time.perf_counter() - clock)
        guessed = None
        if guess:
            part, face = target_part(target_spec), None
            if part is not None:
                try:
                    face = character.found_or_whole([part])
                except Exception:   # batch_clone finds it on its own object, or says why not
                    part = None
            send("face", part, face)
            if face is not None:
                guessed = cloned(source, face, None, progress)
        face, landmarks = connection.recv()
        send("cloned", guessed if face is None else cloned(source, face, landmarks, progress))
    except (EOFError, BrokenPipeError, KeyboardInterrupt):  # batch_clone stopped: so does this
        return
    except Exception as exc:  # batch_clone reports it
        if os.environ.get("EXCLONE_DEBUG"):
            traceback.print_exc()
        try:
            send("error", exc)
        except (pickle.PicklingError, TypeError, AttributeError):
            send("error", RuntimeError(user_message(exc)))
