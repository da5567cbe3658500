"""Blender objects <-> core arrays, vectorised with foreach_get/foreach_set (no per-vertex loops).

Coordinates are always the mesh's own (local) coordinates: the object's transform is never applied,
so deltas written back line up with the vertices they were computed from.
"""
import bpy
import numpy as np

from ..core.errors import ExCloneError
from ..core.mesh import MeshError, PolyMesh


def _read(collection, attribute, count, width, dtype):
    values = np.empty(count * width, dtype=dtype)
    collection.foreach_get(attribute, values)
    return values.reshape(count, width) if width > 1 else values


def _mesh_data(obj, what):
    if obj is None or obj.type != 'MESH':
        kind = "nothing" if obj is None else f"a {obj.type.lower()} object"
        raise MeshError(f"{what} must be a mesh object, got {kind}")
    return obj.data


def checked_editable(obj):
    """obj, or ExCloneError if it or its mesh is linked from a library: linked data is read-only,
    so shape keys or landmarks written to it would be gone after save and reload."""
    if obj.library is not None or obj.data.library is not None:
        raise ExCloneError(f"'{obj.name}' is linked from a library (read-only): make it local "
                           "first (Object > Relations > Make Local)")
    return obj


def _polymesh(me):
    vertices = _read(me.vertices, "co", len(me.vertices), 3, np.float32)
    totals = _read(me.polygons, "loop_total", len(me.polygons), 1, np.int32)
    loops = _read(me.loops, "vertex_index", len(me.loops), 1, np.int32)
    return PolyMesh(vertices.astype(np.float64), totals.astype(np.int64), loops.astype(np.int64))


def mesh_from_object(obj, *, evaluated=False, depsgraph=None, what="object"):
    """The object's mesh as a PolyMesh in local coordinates.

    evaluated=False (default) reads the original mesh data: modifiers and shape key values are
    ignored, so vertex ids match the shape keys. evaluated=True reads the mesh after modifiers and
    the current shape key mix (needs `depsgraph`, e.g. context.evaluated_depsgraph_get()); its
    vertices may not correspond to the original ones.
    """
    me = _mesh_data(obj, what)
    if not evaluated:
        return _polymesh(me)
    obj_eval = obj.evaluated_get(depsgraph)
    try:
        return _polymesh(obj_eval.to_mesh())
    finally:
        obj_eval.to_mesh_clear()


def _key_coordinates(key_block, n_vertices):
    return _read(key_block.data, "co", n_vertices, 3, np.float32).astype(np.float64)


def shape_keys_from_object(obj, what="object"):
    """(names, deltas): every shape key except the reference (basis) key, as (E, n, 3) float64
    displacements from the reference key, whatever key each one is relative to in Blender."""
    me = _mesh_data(obj, what)
    n = len(me.vertices)
    key = me.shape_keys
    if key is None or len(key.key_blocks) < 2:
        return [], np.zeros((0, n, 3))
    reference = key.reference_key
    base = _key_coordinates(reference, n)
    blocks = [kb for kb in key.key_blocks if kb.name != reference.name]
    deltas = np.stack([_key_coordinates(kb, n) - base for kb in blocks])
    return [kb.name for kb in blocks], deltas


def write_shape_keys(obj, names, deltas, *, replace_existing=False):
    """Write deltas (E, n, 3) as shape keys relative to the reference key (a "Basis" key is made
    from the mesh if there is none). An existing key with the same name is left untouched unless
    replace_existing; the reference key itself is never written.

    Returns (added, replaced, skipped): lists of key names.
    """
    me = _mesh_data(obj, "target")
    n = len(me.vertices)
    deltas = np.asarray(deltas, dtype=np.float64)
    if deltas.shape != (len(names), n, 3):
        raise MeshError(f"{obj.name}: expected deltas of shape ({len(names)}, {n}, 3), "
                        f"got {deltas.shape}")
    if me.shape_keys is None:
        obj.shape_key_add(name="Basis", from_mix=False)
    key_blocks = me.shape_keys.key_blocks
    reference = me.shape_keys.reference_key
    base = _key_coordinates(reference, n)
    added, replaced, skipped = [], [], []
    for name, delta in zip(names, deltas):
        block = key_blocks.get(name)
        if block is not None and (not replace_existing or block.name == reference.name):
            skipped.append(name)
            continue
        if block is None:
            block = obj.shape_key_add(name=name, from_mix=False)
            block.value = 0.0    # bpy 5 adds keys at 1.0: every new expression would show at once
            added.append(name)
        else:
            block.relative_key = reference
            replaced.append(name)
        block.data.foreach_set("co", (base + delta).astype(np.float32).ravel())
    me.update()
    return added, replaced, skipped


def object_from_mesh(name, mesh, collection=None):
    """A new mesh object holding `mesh` (PolyMesh) in its local coordinates, linked to
    `collection` (default: the scene's collection). Vertex order is kept."""
    me = bpy.data.meshes.new(name)
    totals = np.asarray(mesh.loop_totals, dtype=np.int64)
    me.vertices.add(len(mesh.vertices))
    me.loops.add(len(mesh.loop_vertices))
    me.polygons.add(len(totals))
    me.vertices.foreach_set("co", np.asarray(mesh.vertices, dtype=np.float32).ravel())
    me.loops.foreach_set("vertex_index", np.asarray(mesh.loop_vertices, dtype=np.int32))
    # Polygon sizes follow from the start offsets (loop_total is read-only since Blender 4.0).
    starts = np.concatenate([[0], np.cumsum(totals)[:-1]]).astype(np.int32)
    me.polygons.foreach_set("loop_start", starts)
    # Repairs invalid faces (which could crash Blender) but never adds, removes or reorders vertices.
    me.validate()
    me.update()
    obj = bpy.data.objects.new(name, me)
    (collection or bpy.context.scene.collection).objects.link(obj)
    return obj
