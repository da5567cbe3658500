"""What the operators share: which meshes and landmarks go in, running the engine once per set
of inputs (a cache), and the options applied to its result.

A source is a core.library.ExpressionLibrary (the built-in library, or one read from a mesh
object's shape keys) plus, kept here beside it, the Blender object it came from (None for the
built-in library), whose stored landmarks count. Meshes are read from the base mesh (modifiers
are not applied, so vertex ids match the shape keys); a target with shape keys is read at its
reference (basis) key.

A target is a character (blender/character.py): its mesh objects are read in world space, the
face is found on them (core.character), and only the head region of the face's object is
solved; its keys are written back in that object's local coordinates.
"""
import hashlib
import threading
from collections import OrderedDict
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..core import character as core_character
from ..core.cloning import CloneSettings, fit_faces, found_landmarks, transfer_expressions
from ..core.errors import Cancelled, ExCloneError
from ..core.expression_measures import measure_clone, summary
from ..core import data
from ..core.landmarks import checked_pairs
from ..core.library import ExpressionLibrary, load_library
from ..core.mesh import PolyMesh, vertex_parts, welded
from . import character
from . import landmarks as stored_landmarks
from . import mesh_io, preferences

CACHE_SIZE = 3
# Blender keeps at most 63 bytes of a name (64 with the terminating NUL), cut at a character.
MAX_NAME_BYTES = 63


@dataclass
class Run:
    result: object                # core.cloning.CloneResult for every source expression, or
                                  # the FaceFit alone (Register)
    landmark_kind: str            # "automatic" (soft) or "edited" (hard constraints)
    cached: bool


def has_shape_keys(obj):
    return obj.type == 'MESH' and obj.data.shape_keys is not None and \
        len(obj.data.shape_keys.key_blocks) > 1


def settings_of(context):
    return context.scene.exclone


def target_object(context):
    """The scene's chosen target, else the active object (may be None or not a mesh)."""
    return settings_of(context).target or context.active_object


def source_object(context, target):
    """The scene's chosen source object, else the one selected mesh with shape keys outside the
    target's character (its hierarchy). Raises ExCloneError if there is none or several."""
    chosen = settings_of(context).source
    if chosen is not None:
        return chosen
    own = [target, *character.family(target)] if target is not None else []
    candidates = [obj for obj in context.selected_objects
                  if obj not in own and has_shape_keys(obj)]
    if not candidates:
        raise ExCloneError("Select a source mesh with shape keys as well as the target "
                           "(active), or enable Built-in Library")
    if len(candidates) > 1:
        raise ExCloneError("Several selected meshes have shape keys ("
                           + ", ".join(obj.name for obj in candidates) + "): select only one source")
    return candidates[0]


@lru_cache(maxsize=1)
def _library(path):
    return load_library(path)


def library_source():
    """The built-in library (read once; shared, so never changed in place)."""
    return _library(data.LIBRARY_FILE)


@lru_cache(maxsize=1)
def arkit_source():
    """What Generate ARKit Shapes clones: the built-in library with a tongueOut of its own
    (ExpressionLibrary.with_tongue_out), so that the clone makes it on every part of the target,
    a one-mesh head's own tongue included (made once; shared, never changed in place)."""
    return library_source().with_tongue_out()


def object_source(obj, description=None):
    """The expressions of a mesh object's shape keys as an ExpressionLibrary. The face is found
    on the object as on a target (character_face), and only its head region is the source (a
    full body's keys are taken at its face; core.character.source_head); an object on which no
    face is found, or whose landmarks were edited (placed on the whole mesh), is used whole.
    description: what reports call it (default: the object's name)."""
    if obj.type != 'MESH':
        raise ExCloneError(f"Source '{obj.name}' is not a mesh")
    if not has_shape_keys(obj):
        raise ExCloneError(f"Source '{obj.name}' has no shape keys to clone")
    names, deltas = mesh_io.shape_keys_from_object(obj, what="source")
    whole = ExpressionLibrary(basis_mesh(obj, "source"), names, deltas,
                              description=description or f"'{obj.name}'")
    if stored_landmarks.is_edited(obj):
        return whole
    face = character_face(character.parts([obj]))
    return core_character.source_head(whole, face)


def resolve_source(context, target, use_library):
    """(the source's ExpressionLibrary, the mesh object it was read from or None for the
    built-in library)."""
    if use_library or settings_of(context).source_mode == 'LIBRARY':
        return library_source(), None
    obj = source_object(context, target)
    if obj == target:
        raise ExCloneError(f"'{obj.name}' is both source and target: choose another source")
    return object_source(obj), obj


def stored_name(name):
    """`name` as Blender stores it (a shape key's, an object's): cut to MAX_NAME_BYTES bytes of
    UTF-8, never inside a character. Names are compared this way, or a long one never matches."""
    return name.encode("utf-8")[:MAX_NAME_BYTES].decode("utf-8", errors="ignore")


def key_names(prefix, names):
    """The new shape keys' names for expressions `names` as Blender will store them; ExCloneError
    if the prefix is so long that two expressions' names would be cut to the same one."""
    stored = [stored_name(prefix + name) for name in names]
    first = {}
    for name, key in zip(names, stored):
        if key in first:
            raise ExCloneError(f"Prefix too long: shape key names keep {MAX_NAME_BYTES} bytes, so "
                               f"'{first[key]}' and '{name}' would both be named '{key}'; use a "
                               "shorter prefix")
        first[key] = name
    return stored


def checked_target(obj):
    if obj is None:
        raise ExCloneError("Nothing selected: make the target head the active object")
    if obj.type != 'MESH':
        raise ExCloneError(f"Target '{obj.name}' is not a mesh")
    return mesh_io.checked_editable(obj)


def basis_mesh(obj, role):
    """The object's base mesh in local coordinates, at its reference key if it has shape keys
    (what the new keys are made relative to)."""
    mesh = mesh_io.mesh_from_object(obj, what=role)
    key = obj.data.shape_keys
    if key is not None:
        co = np.empty(len(obj.data.vertices) * 3, dtype=np.float32)
        key.reference_key.data.foreach_get("co", co)
        mesh = PolyMesh(co.reshape(-1, 3).astype(np.float64), mesh.loop_totals, mesh.loop_vertices)
    return mesh


def landmark_pairs(source, source_obj, target_obj, target_mesh, target_face):
    """None (the engine's automatic, soft landmarks) unless a side carries edited landmarks; then
    {"source": ids, "target": ids} of the names both sides have, as hard constraints.
    source_obj: the object `source` was read from (None: the built-in library); target_face:
    the target's CharacterFace (where the target's automatic landmarks are found).
    Raises ExCloneError for stale, off-surface or too few landmarks."""
    sides = [(source_obj, "source"), (target_obj, "target")]
    for obj, role in sides:
        if obj is not None and stored_landmarks.IDS in obj:
            stored_landmarks.checked(obj, role)
    if not any(obj is not None and stored_landmarks.is_edited(obj) for obj, _ in sides):
        return None

    def ids_of(obj, mesh):
        if obj is None or (obj is source_obj and source.head is not None
                           and stored_landmarks.IDS not in obj):
            return dict(zip(source.automatic_landmarks[0], source.automatic_landmarks[1].tolist()))
        if stored_landmarks.IDS in obj:
            ids = stored_landmarks.stored(obj)
            return ids if obj is not source_obj else _in_source_head(source, ids)
        return face_landmarks(target_face) if obj is target_obj else stored_landmarks.detect(mesh)

    src, tgt = ids_of(source_obj, source.mesh), ids_of(target_obj, target_mesh)
    common = [name for name in src if name in tgt]
    pairs = {"source": [src[n] for n in common], "target": [tgt[n] for n in common]}
    try:
        checked_pairs(pairs, len(source.mesh.vertices), len(target_mesh.vertices))
    except ExCloneError as exc:
        raise ExCloneError(f"{exc} (the landmark names source and target share): run Auto "
                           "Landmarks on both") from exc
    return pairs


def _in_source_head(source, ids):
    """{name: id} of the source object's stored landmarks in the numbering of `source` (its head
    region when it was cut to one). ExCloneError if one lies outside that region."""
    inside = source.ids_from_own(list(ids.values()))
    if inside is None:
        raise ExCloneError(f"The landmarks stored on the source {source.description} lie outside "
                           "its face's head region: run Auto Landmarks again")
    return dict(zip(ids, inside.tolist()))


@dataclass
class Target:
    """The character an engine operator works on: its mesh objects and where its face is."""
    objects: list                 # the character's mesh objects (the face's first found)
    face: object                  # core.character.CharacterFace: the face's object and head
    landmarks: dict               # {"source", "target": ids in the head's numbering} or None

    @property
    def face_object(self):
        return self.objects[self.face.part]

    def others(self):
        """The character's objects other than the face's (eyes, brows, teeth...)."""
        return [obj for obj in self.objects if obj != self.face_object]


def resolve_target(context, source, source_obj):
    """The Target of the operators: the character of the active (or chosen) object, its face
    found, the landmarks (edited ones, if any) in its head's numbering. Raises ExCloneError."""
    context.view_layer.update()       # objects moved by a script: their matrix_world
    objects = character.character_objects(target_object(context), context.selected_objects,
                                          exclude=[source_obj])
    for obj in objects:
        mesh_io.checked_editable(obj)
    return target_of(objects, source, source_obj)


def target_of(objects, source, source_obj=None):
    """The Target of a character's mesh objects (in a scene, transforms evaluated)."""
    parts = character.parts(objects)
    marked = [k for k, obj in enumerate(objects) if stored_landmarks.is_edited(obj)]
    try:
        face = character_face(parts)
    except ExCloneError:
        if not marked:
            raise
        face = core_character.whole(parts[marked[0]], marked[0])
    if marked and face.part != marked[0]:         # edited landmarks say where the face is
        face = core_character.whole(parts[marked[0]], marked[0])
    face_object = objects[face.part]
    landmarks = landmark_pairs(source, source_obj, face_object,
                               basis_mesh(face_object, "target"), face)
    return Target(objects, *in_head(face, parts[face.part], landmarks))


def target_landmarks(context, exclude=()):
    """(the face's object, its automatic landmarks {name: own vertex id}) of the target
    character, found as Clone finds them: on the found face's head region with its guide.
    exclude: objects that are no part of the character (the source). Raises ExCloneError."""
    context.view_layer.update()       # objects moved by a script: their matrix_world
    objects = character.character_objects(target_object(context), context.selected_objects,
                                          exclude=exclude)
    face = character_face(character.parts(objects))
    return objects[face.part], face_landmarks(face)


def source_landmarks(obj):
    """{name: vertex id of obj} of a source object: its automatic landmarks as Clone finds them
    (object_source: on the head region of the face found on it, with the face's guide), else,
    where no face is found, on its whole mesh. Raises ExCloneError."""
    face = character_face(character.parts([obj]))
    if face.guide is None:
        return stored_landmarks.detect(basis_mesh(obj, obj.name))
    return face_landmarks(face)


def face_landmarks(face):
    """{name: vertex id of the face's object} of a CharacterFace: its automatic landmarks as
    Clone finds them, on its head region with its guide. Raises ExCloneError."""
    names, ids = found_landmarks(face.head.mesh, "target", face_guide=face.guide)
    return dict(zip(names, (int(i) for i in face.head.own_ids(ids))))


def in_head(face, part, landmarks):
    """(face, landmarks) with the given landmark pairs' target ids (the face object's own
    numbering) in its head's; where one lies outside the head, the object is solved whole (its
    Part) with them as they are. landmarks None: (face, None)."""
    if landmarks is None:
        return face, None
    inside = face.head.head_ids(landmarks["target"])
    if inside is None:
        return core_character.whole(part, face.part), landmarks
    return face, {"source": list(landmarks["source"]), "target": inside.tolist()}


def face_object_deltas(obj, face, head_deltas):
    """(E, n, 3) the head's world-space deltas (E, m, 3) as the face's object's own (obj; face:
    its CharacterFace): in its local coordinates, zero outside the head."""
    return character.local_deltas(obj, face.head.spread(face.to_world(head_deltas)))


def write_face_keys(target, names, head_deltas, replace_existing):
    """The head's world-space deltas (E, m, 3) as shape keys of the face's object (Target), in
    its local coordinates (zero outside the head); (added, replaced, skipped) key names."""
    return mesh_io.write_shape_keys(target.face_object, names,
                                    face_object_deltas(target.face_object, target.face,
                                                       head_deltas),
                                    replace_existing=replace_existing)


def character_face(parts):
    """core.character.found_or_whole on the character's parts (world space), remembered for
    the same meshes."""
    key = digest(*[value for part in parts for value in (
        part.name, part.mesh.vertices, part.mesh.loop_totals, part.mesh.loop_vertices)])
    if key not in _faces:
        remember(_faces, key, core_character.found_or_whole(parts))
    _faces.move_to_end(key)
    return _faces[key]


def digest(*parts):
    """A key for a cache: arrays by their bytes, anything else by its repr."""
    h = hashlib.sha1()
    for part in parts:
        h.update(np.ascontiguousarray(part).tobytes() if isinstance(part, np.ndarray)
                 else repr(part).encode())
    return h.hexdigest()


_faces = OrderedDict()      # character meshes -> core.character.CharacterFace (or the error)
_fits = OrderedDict()       # fit key -> core.cloning.FaceFit
_results = OrderedDict()    # fit key + expressions -> core.cloning.CloneResult


def clear_cache():
    _faces.clear()
    _fits.clear()
    _results.clear()


def remember(cache, key, value, size=CACHE_SIZE):
    """Put value in an OrderedDict cache, dropping the oldest entries beyond `size`."""
    cache[key] = value
    while len(cache) > size:
        cache.popitem(last=False)


def run_engine(source, target, landmarks, clone_settings, transfer=True, progress=None):
    """The engine's fit of source onto target (transfer=False: Register), or its result for
    every source expression (transfer=True: Clone). target: a core.character.CharacterFace (its
    head mesh is solved, guided by the found face, its cut held still; landmarks in the head's
    numbering) or a PolyMesh used whole. The fit is reused while the meshes, the landmarks and
    the settings are unchanged, so Clone after Register only transfers; Run.cached says whether
    it was."""
    if isinstance(target, PolyMesh):
        target = core_character.whole(core_character.Part("target", target), 0)
    target_mesh = target.head.mesh
    guide = target.guide if landmarks is None else None     # it only guides automatic ones
    key = digest(source.mesh.vertices, source.mesh.loop_totals, source.mesh.loop_vertices,
                  target_mesh.vertices, target_mesh.loop_totals, target_mesh.loop_vertices,
                  target.head.fixed, *_guide_parts(guide), landmarks, clone_settings)
    kind = "automatic" if landmarks is None else "edited"
    cached = key in _fits
    if cached:
        _fits.move_to_end(key)
        fit = _fits[key]
    else:
        def fit_progress(fraction, message):
            if progress:
                progress(fraction * (0.8 if transfer else 1.0), message)

        try:
            fit = fit_faces(source.mesh, target_mesh, landmarks=landmarks,
                            source_landmarks=source.automatic_landmarks,
                            source_modes=source.shape_modes, settings=clone_settings,
                            progress=fit_progress, face_guide=guide,
                            fixed_vertices=target.head.fixed,
                            shared_vertices=core_character.shared_vertices(source, target))
        except ExCloneError as error:
            if target.not_found is None or landmarks is not None:
                raise
            # neither rendering nor the mesh's geometry found the face: say what to do
            raise ExCloneError(f"{target.not_found} (by its geometry: {error})") from error
        remember(_fits, key, fit)
    if transfer:
        result_key = key + digest(source.deltas, source.names)
        if result_key not in _results:
            if progress:
                progress(0.8, "transfer")
            remember(_results, result_key, transfer_expressions(fit, source.deltas, source.names))
        _results.move_to_end(result_key)
    if progress:
        progress(1.0, "done")
    return Run(_results[result_key] if transfer else fit, kind, cached)


def _guide_parts(guide):
    """What identifies a FaceGuide in a cache key."""
    if guide is None:
        return (None,)
    return (guide.frame.rotation, guide.frame.origin, list(guide.points),
            np.stack(list(guide.points.values())), guide.eye_distance)


def clone_settings(context, preset, formulation):
    if preset in ("", "DEFAULT"):
        preset = preferences.default_preset(context)
    return CloneSettings(preset=preset, formulation=formulation)


def still_parts_mask(target_mesh, target_landmarks):
    """Vertices of the parts without landmarks (they keep their shape with parts='STILL').
    Parts of the welded mesh, as the engine sees them: pieces an exporter split at UV seams are
    one part."""
    joined, index = welded(target_mesh)
    parts = vertex_parts(len(joined.vertices), joined.triangles())[index]
    return ~np.isin(parts, parts[np.asarray(target_landmarks)])


# The last Clone's expression measures, for the panel: {"target": object name, "summary":
# core.expression_measures.summary}; empty before the first Clone of the session.
last_measures = {}


def measure(target_name, target_mesh, result, names, deltas, source=None):
    """The expression measures of the shape keys a Clone wrote (names, deltas), kept as the
    last run's for the panel; returns their summary. source: the clone's source (an
    ExpressionLibrary), for the stretch beyond the source's own (excess_stretch)."""
    source_deltas = None if source is None else \
        source.deltas[[source.names.index(name) for name in names]]
    found = summary(measure_clone(target_mesh, result, names, deltas,
                                  source=None if source is None else source.mesh,
                                  source_deltas=source_deltas))
    last_measures.clear()
    last_measures.update(target=target_name, summary=found)
    return found


def usable_source_object(context, target):
    """The source object resolve_source would read (source_object, in Object source mode), or
    None where there is none it could use (the built-in library, none or several chosen, the
    target itself, no mesh): for the steps that only prepare or edit, and leave the message to
    resolve_source."""
    if settings_of(context).source_mode != 'OBJECT':
        return None
    try:
        source = source_object(context, target)
    except ExCloneError:
        return None
    return source if source.type == 'MESH' and source is not target else None


def face_searches(context, use_library, every_source=False):
    """The parts lists whose face the operators' resolve_source and resolve_target will look
    for: the source object's (unless it is the built-in library, or its landmarks were edited
    and every_source is False: object_source then uses it whole) and the target character's,
    read now (main thread) for a FaceSearch. What cannot be resolved is left out: the operator
    itself reports it."""
    target = target_object(context)
    searches = []
    source_obj = None if use_library else usable_source_object(context, target)
    if source_obj is not None and (every_source or not stored_landmarks.is_edited(source_obj)):
        searches.append(character.parts([source_obj]))
    context.view_layer.update()       # as resolve_target: objects moved by a script
    try:
        searches.append(character.parts(character.character_objects(
            target, context.selected_objects, exclude=[source_obj])))
    except ExCloneError:
        pass
    return searches


class _Worker:
    """self._work(*args) in a daemon thread: start(), done, wait()."""

    def __init__(self, *args):
        self._thread = threading.Thread(target=self._work, args=args, daemon=True)

    def start(self):
        self._thread.start()
        return self

    @property
    def done(self):
        return not self._thread.is_alive()

    def wait(self, timeout=None):
        self._thread.join(timeout)
        return self.done


class FaceSearch(_Worker):
    """character_face of parts lists (face_searches) in a worker thread: the face finding's
    renders and models take 1-3 s on a character the first time, which froze Blender before the
    engine's own worker started. The faces wait in character_face's memory for the operator's
    own call on the main thread; a search that fails is left for that call to report."""

    @staticmethod
    def _work(searches):
        for parts in searches:
            try:
                character_face(parts)
            except Exception:       # reported by the operator's own call
                pass


class EngineJob(_Worker):
    """run_engine in a worker thread, so that the UI stays responsive and Esc can stop it.

    The worker touches no Blender data (the meshes are read before, the result is written after,
    in the main thread). cancel() makes the engine's next progress call raise Cancelled.
    """

    def __init__(self, *inputs):
        """inputs: run_engine's (source, target mesh, landmarks, settings[, transfer])."""
        self.fraction, self.message = 0.0, "starting"
        self.run = self.error = None
        self._cancel = threading.Event()
        super().__init__(*inputs)

    def _progress(self, fraction, message):
        if self._cancel.is_set():
            raise Cancelled()
        self.fraction, self.message = fraction, message

    def _work(self, *inputs):
        try:
            self.run = run_engine(*inputs, progress=self._progress)
        except Exception as exc:  # any, Cancelled too: the operator reports it in the main thread
            self.error = exc

    def cancel(self):
        self._cancel.set()

    @property
    def cancelled(self):
        return self._cancel.is_set()


def mesh_digest(obj):
    """Identifies an object's basis mesh, to notice edits made while a job runs."""
    mesh = basis_mesh(obj, "target")
    return digest(mesh.vertices, mesh.loop_totals, mesh.loop_vertices)
