"""A character in Blender: its mesh objects, read in world space for the solve, and world-space
results written back in each object's own (local) coordinates.

The engine works in world space so that object transforms (an unapplied rotation, a centimetre
scale, a parent) do not matter: every object of a character is read through its matrix_world,
and a world-space displacement d of a vertex is the local one M^-1 d, with M the 3x3 part of
matrix_world (translation does not change a displacement).
"""
from typing import NamedTuple

import numpy as np

from ..core.character import Part
from ..core.errors import ExCloneError
from ..core.mesh import PolyMesh
from . import mesh_io


class WorldMesh(NamedTuple):
    vertices: np.ndarray      # (n, 3) float64 basis positions in world space
    triangles: np.ndarray     # (t, 3) int64 vertex ids (the polygons triangulated)


def basis_coordinates(obj):
    """(n, 3) the object's base mesh in local coordinates, at its reference key if it has shape
    keys (what new keys are made relative to)."""
    me = obj.data
    key = me.shape_keys
    if key is None:
        co = np.empty(len(me.vertices) * 3, dtype=np.float32)
        me.vertices.foreach_get("co", co)
    else:
        co = np.empty(len(me.vertices) * 3, dtype=np.float32)
        key.reference_key.data.foreach_get("co", co)
    return co.reshape(-1, 3).astype(np.float64)


def linear_part(obj):
    """(3, 3) the rotation/scale/shear part of the object's matrix_world."""
    return np.array(obj.matrix_world, dtype=np.float64)[:3, :3]


def to_world(obj, local_points):
    """(n, 3) local positions of obj in world space."""
    matrix = np.array(obj.matrix_world, dtype=np.float64)
    return np.asarray(local_points, dtype=np.float64) @ matrix[:3, :3].T + matrix[:3, 3]


def world_polymesh(obj, what="target"):
    """The object's base mesh (basis key) as a PolyMesh in world space, its polygons as in
    Blender (vertex ids match the shape keys)."""
    local = mesh_io.mesh_from_object(obj, what=what)
    return PolyMesh(to_world(obj, basis_coordinates(obj)), local.loop_totals, local.loop_vertices)


def world_mesh(obj):
    """WorldMesh (vertices, triangles) of the object's basis mesh in world space."""
    mesh = world_polymesh(obj, what=obj.name)
    return WorldMesh(mesh.vertices, mesh.triangles())


def local_deltas(obj, world_deltas):
    """World-space displacements (..., n, 3) of obj's vertices in its local coordinates: through
    the inverse of the 3x3 part of matrix_world. ExCloneError if the object is flattened (a zero
    scale), as no local displacement then gives the world one."""
    linear = linear_part(obj)
    if abs(np.linalg.det(linear)) < 1e-30 * max(np.abs(linear).max(), 1e-300) ** 3:
        raise ExCloneError(f"'{obj.name}' has a zero scale on some axis: apply or fix its "
                           "scale first")
    return np.asarray(world_deltas, dtype=np.float64) @ np.linalg.inv(linear).T


def family(obj):
    """The mesh objects of obj's hierarchy: its top-most parent and everything under it."""
    root = obj
    while root.parent is not None:
        root = root.parent
    return [one for one in [root, *root.children_recursive] if one.type == 'MESH']


def character_objects(target, selected=(), exclude=()):
    """The character's mesh objects, given the target object (active or chosen; may be the
    character's empty parent): its hierarchy when it has one, else the selected meshes with it
    (or it alone). Objects in `exclude` (the source) are never part of it. ExCloneError if
    there is no mesh."""
    if target is None:
        raise ExCloneError("Nothing selected: make the character (or its head) the active "
                           "object")
    meshes = [obj for obj in family(target) if obj not in exclude]
    if len(meshes) <= 1:          # no hierarchy of meshes: the selection makes the character
        meshes += [obj for obj in selected if obj.type == 'MESH' and obj not in exclude
                   and obj not in meshes]
    if not meshes:
        raise ExCloneError(f"'{target.name}' is not a mesh and has no mesh objects under it: "
                           "select the character's mesh objects")
    return sorted(meshes, key=lambda obj: obj != target)       # the target first


def parts(objects):
    """core.character.Part (world space) of each object."""
    return [Part(obj.name, world_polymesh(obj, what=obj.name)) for obj in objects]
