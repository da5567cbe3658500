"""What the command lines read without Blender: file specs ('file.blend:Object'), the file types,
and the sources that are plain files (a folder of neutral.obj + one OBJ per expression, or the
bundled library). blender/files.py reads everything else through Blender.

No bpy here: batch_clone.py reads a source of plain files in a process that has not loaded
Blender (scripts/clone_worker.py).
"""
import math
from pathlib import Path

from ..core import library
from ..core.errors import ExCloneError
from ..core.mesh import MeshError, check_mesh

IMPORTERS = {".fbx": "fbx", ".glb": "gltf", ".gltf": "gltf"}
CONTAINERS = (".blend",) + tuple(IMPORTERS)
TARGET_SUFFIXES = (".obj",) + CONTAINERS
RESULT_SUFFIXES = (".blend", ".glb", ".fbx")
# An OBJ target's object is turned by this (Euler XYZ, radians): OBJ is Y-up, Blender Z-up
OBJ_ROTATION = (math.pi / 2, 0.0, 0.0)


def split_spec(spec):
    """'file.blend:Object' -> (Path('file.blend'), 'Object'); anything else -> (Path, None)."""
    head, sep, name = spec.rpartition(":")
    if sep and Path(head).suffix.lower() in CONTAINERS and name and not Path(spec).exists():
        return Path(head), name
    return Path(spec), None


def source_is_plain_files(spec):
    """True if load_source reads this source without Blender (the bundled library, a folder of
    OBJs): the command line then need not reset Blender's scene for it."""
    return spec is None or split_spec(spec)[0].is_dir()


def existing(path, role):
    if not path.exists():
        raise ExCloneError(f"{role} not found: {path}")
    return path


def checked(mesh, what):
    """The mesh if the engine can use it (core.mesh.check_mesh); errors start with `what`."""
    try:
        triangles = mesh.triangles()
    except MeshError as exc:    # triangulation errors do not say which mesh
        raise MeshError(f"{what}: {exc}") from exc
    check_mesh(mesh.vertices, triangles, what=what)
    return mesh


def load_source(spec, role="source", read_container=None):
    """The expressions of a source spec as a core.library.ExpressionLibrary whose description
    names the file (and object): None = the bundled library, a folder of OBJs, or (through
    read_container(path, object name or None, role), which Blender does) a .blend[:Object],
    .fbx, .glb or .gltf mesh with shape keys."""
    if spec is None:
        source = library.load_library()
    else:
        path, name = split_spec(spec)
        suffix = existing(path, role).suffix.lower()
        if path.is_dir():
            source = library.load_obj_folder(path)
        elif suffix == ".obj":
            raise ExCloneError(f"{role} {path} is an OBJ file, which cannot hold shape keys: "
                               "give a folder with neutral.obj + one OBJ per expression, or a "
                               ".blend, .fbx or .glb mesh with shape keys")
        elif suffix in CONTAINERS:
            source = read_container(path, name, role)
        else:
            raise ExCloneError(f"{role} {path}: unsupported file type '{path.suffix}' "
                               "(use .blend, .fbx, .glb or a folder of OBJs)")
    checked(source.mesh, f"{role} {source.description}")
    if not source.names:
        raise ExCloneError(f"{role} {source.description} has no expressions")
    return source
