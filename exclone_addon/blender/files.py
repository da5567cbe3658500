"""Meshes from files, for the command lines: a .blend[:Object] (appended from, never linked), an
.fbx, .glb or .gltf (imported into the current scene), an .obj (read by core.mesh.read_obj: the
file's coordinates and vertex order are kept) or a folder with neutral.obj + one OBJ per
expression (core.library.load_obj_folder). Input files are only read.

A target file is a character: without :Object every mesh object of the file is, with :Object
that object and its hierarchy; the face is found on them (blender/workflow.character_face). A
source file's object (:Object, else its first mesh with shape keys by name) is read as the
operators read a source object: the face is found on it and only its head region's motion is
the source (workflow.object_source), so a full body with expression keys is a source.
"""
from dataclasses import dataclass
from pathlib import Path

import bpy

from ..core import data
from ..core.errors import ExCloneError
from ..core.mesh import PolyMesh, read_obj
from . import character, mesh_io, plain_files, workflow
from .plain_files import CONTAINERS, IMPORTERS, split_spec


@dataclass
class Target:
    description: str
    mesh: PolyMesh                  # the face's object's mesh, its own coordinates
    obj: object                     # the face's object, in the current scene: it gets the keys
    objects: list                   # the character's mesh objects in the scene (obj among them)
    face: object                    # core.character.CharacterFace: the face's object and head


def _has_shape_keys(obj):
    return obj.data.shape_keys is not None and len(obj.data.shape_keys.key_blocks) > 1


def _objects_from_file(path):
    """Every object of a .blend (appended, not linked to a scene) or of an imported FBX/glTF."""
    if path.suffix.lower() == ".blend":
        try:
            with bpy.data.libraries.load(str(path), link=False) as (data_from, data_to):
                data_to.objects = list(data_from.objects)
        except OSError as exc:
            raise ExCloneError(f"{path} is not a readable .blend file") from exc
        return [obj for obj in data_to.objects if obj is not None]
    before = set(bpy.data.objects)
    importer = getattr(bpy.ops.import_scene, IMPORTERS[path.suffix.lower()])
    try:
        importer(filepath=str(path))
    except RuntimeError as exc:
        raise ExCloneError(f"cannot import {path}: {_first_line(exc, 'import failed')}") from exc
    return [obj for obj in bpy.data.objects if obj not in before]


def _first_line(error, default):
    text = str(error).strip()
    return text.splitlines()[0].removeprefix("Error: ") if text else default


def _named_object(objects, path, name, role, need_shape_keys):
    chosen = next((obj for obj in objects if obj.name == name), None)
    if chosen is None:
        available = ", ".join(obj.name for obj in objects[:10]) or "none"
        raise ExCloneError(f"{role} {path} has no object named '{name}' (objects: {available})")
    if chosen.type != 'MESH':
        raise ExCloneError(f"{role} {path}:{name} is not a mesh object")
    if need_shape_keys and not _has_shape_keys(chosen):
        raise ExCloneError(f"{role} {path}:{name} has no shape keys")
    return chosen


def pick_object(path, name, role, need_shape_keys):
    """The object `name` of the file, else its first mesh object by name (with shape keys if
    need_shape_keys). role ("source", "target", ...) starts every error message."""
    objects = sorted(_objects_from_file(path), key=lambda obj: obj.name)
    if name is not None:
        return _named_object(objects, path, name, role, need_shape_keys)
    meshes = [obj for obj in objects if obj.type == 'MESH']
    if not meshes:
        raise ExCloneError(f"{role} {path} contains no mesh object")
    if need_shape_keys:
        meshes = [obj for obj in meshes if _has_shape_keys(obj)]
        if not meshes:
            raise ExCloneError(f"{role} {path} has no mesh object with shape keys")
    return meshes[0]


def _library_from_file(path, name, role):
    """The object's shape keys as the Blender operators read a source object
    (workflow.object_source: a full body's head region only)."""
    obj = pick_object(path, name, role, need_shape_keys=True)
    bpy.context.view_layer.update()          # imported objects: their matrix_world
    return workflow.object_source(obj, description=f"{path}:{obj.name}")


def load_source(spec, role="source"):
    """plain_files.load_source, a .blend[:Object], .fbx, .glb or .gltf source read through
    Blender."""
    return plain_files.load_source(spec, role, read_container=_library_from_file)


def _keep_only(objects):
    """Remove every object but `objects` and their parents, and link them to the scene (their
    transforms evaluated): the file saved afterwards holds the target alone (and what it
    uses)."""
    keep = set()
    for obj in objects:
        while obj is not None:
            keep.add(obj)
            obj = obj.parent
    bpy.data.batch_remove([other for other in bpy.data.objects if other not in keep])
    scene = bpy.context.scene
    for obj in sorted(keep, key=lambda one: one.name):
        if obj.name not in scene.collection.all_objects:
            scene.collection.objects.link(obj)
    bpy.context.view_layer.update()


def _character_in(path, name):
    """The character's objects of a file: the object `name` and its hierarchy, else every mesh
    object (a file of several characters is not told apart: give :Object)."""
    objects = sorted(_objects_from_file(path), key=lambda obj: obj.name)
    if name is not None:
        return character.family(_named_object(objects, path, name, "target", False))
    meshes = [obj for obj in objects if obj.type == 'MESH']
    if not meshes:
        raise ExCloneError(f"target {path} contains no mesh object")
    return meshes


def load_target(spec, find_face=workflow.character_face):
    """The target spec (None = the bundled demo head) as a Target whose object sits in the
    current scene, alone, its face found by find_face(character.parts(objects)). An OBJ becomes
    a new object whose mesh keeps the file's coordinates, rotated by plain_files.OBJ_ROTATION
    (+90 degrees about X: OBJ is Y-up, Blender Z-up)."""
    path, name = (data.DEMO_HEAD_FILE, None) if spec is None else split_spec(spec)
    suffix = plain_files.existing(path, "target").suffix.lower()
    if path.is_dir():
        raise ExCloneError(f"target {path} is a folder; give a .blend, .obj, .fbx or .glb file")
    if suffix == ".obj":
        obj = mesh_io.object_from_mesh(path.stem,
                                       plain_files.checked(read_obj(path), f"target {path}"))
        obj.rotation_euler = plain_files.OBJ_ROTATION
        objects = [obj]
    elif suffix in CONTAINERS:
        objects = _character_in(path, name)
    else:
        raise ExCloneError(f"target {path}: unsupported file type '{path.suffix}' "
                           "(use .blend, .obj, .fbx or .glb)")
    for obj in objects:
        mesh_io.checked_editable(obj)
    _keep_only(objects)
    face = find_face(character.parts(objects))
    obj = objects[face.part]
    description = str(path) if suffix == ".obj" else f"{path}:{obj.name}"
    mesh = plain_files.checked(mesh_io.mesh_from_object(obj, what="target"),
                               f"target {description}")
    return Target(description, mesh, obj, objects, face)


# -- writing ------------------------------------------------------------------------------------

# The first bytes of a whole file of each exported type (a cut-short write lacks them or is empty).
_MAGIC = {".glb": b"glTF", ".fbx": b"Kaydara FBX Binary"}


def save_result(path, objects):
    """Write the result at `path` by its suffix: a .blend copy of the current file (save_copy),
    or `objects` exported through Blender's own glTF (.glb) or FBX exporter with their shape
    keys as morph targets / blend shapes of the same names. OSError with the reason if the file
    was not written whole."""
    suffix = Path(path).suffix.lower()
    if suffix == ".blend":
        save_copy(path, holds=objects[0].name)
    elif suffix in _MAGIC:
        export_objects(path, objects)
    else:
        raise ExCloneError(f"cannot write {path}: use .blend, .glb or .fbx")


def export_objects(path, objects):
    """objects (with their parents) as a .glb or .fbx at `path`, as they are: no modifier is
    applied (that would drop the shape keys), no animation; the exporters convert Blender's Z-up
    to the formats' Y-up, and their importers convert it back."""
    path = Path(path).resolve()
    for obj in bpy.context.view_layer.objects:
        obj.select_set(False)
    for obj in objects:
        while obj is not None:
            obj.select_set(True)
            obj = obj.parent
    try:
        if path.suffix.lower() == ".glb":
            result = bpy.ops.export_scene.gltf(
                filepath=str(path), export_format='GLB', use_selection=True, export_apply=False,
                export_morph=True, export_morph_normal=False, export_animations=False)
        else:
            result = bpy.ops.export_scene.fbx(
                filepath=str(path), use_selection=True, use_mesh_modifiers=False,
                bake_anim=False, add_leaf_bones=False)
    except RuntimeError as exc:
        raise OSError(_first_line(exc, "Blender could not export it")) from exc
    if result != {'FINISHED'} or not path.is_file():
        raise OSError("Blender did not export it")
    with path.open("rb") as handle:
        if handle.read(len(_MAGIC[path.suffix.lower()])) != _MAGIC[path.suffix.lower()]:
            raise OSError("the exported file is incomplete; is the disk full?")


def save_copy(path, holds):
    """Save the current file's data as a copy at `path` (the session keeps its own file path),
    then read it back: a full disk can leave a truncated file that Blender reports as saved.
    holds: the name of an object the saved file must list. OSError with the reason if the file
    was not saved whole (a full disk, a read-only folder)."""
    path = Path(path).resolve()
    try:
        result = bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True, check_existing=False)
    except RuntimeError as exc:
        raise OSError(_first_line(exc, "Blender could not save it")) from exc
    if result != {'FINISHED'} or not path.is_file():
        raise OSError("Blender did not save it")
    try:
        with bpy.data.libraries.load(str(path)) as (saved, _):
            names = list(saved.objects)
    except OSError as exc:
        raise OSError("the saved file cannot be read back (truncated?); is the disk full?") \
            from exc
    if holds not in names:
        raise OSError(f"the saved file lacks the object '{holds}'; is the disk full?")
