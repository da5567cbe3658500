"""Blender objects <-> core arrays (exclone_addon.blender.mesh_io) on the bundled demo head."""

import bpy
import numpy as np
import pytest

from exclone_addon.core import data
from exclone_addon.blender import mesh_io
from exclone_addon.core.mesh import MeshError, read_obj

DEMO_HEAD = data.DEMO_HEAD_FILE


@pytest.fixture
def head():
    return read_obj(DEMO_HEAD)


def smooth_deltas(vertices, count):
    """Distinct, deterministic per-vertex displacements (one 'expression' per row)."""
    scale = np.ptp(vertices, axis=0).max()
    return np.stack([0.01 * scale * np.sin((k + 1) * vertices / scale + k) for k in range(count)])


def stored(base, delta):
    """What a shape key holds for base + delta, read back as a delta (Blender keeps float32)."""
    base32 = base.astype(np.float32)
    return (base32 + delta).astype(np.float32).astype(np.float64) - base32


def test_polymesh_round_trip_keeps_vertices_and_polygons(head):
    obj = mesh_io.object_from_mesh("head", head)
    back = mesh_io.mesh_from_object(obj)
    assert np.array_equal(back.vertices, head.vertices.astype(np.float32))
    assert np.array_equal(back.loop_totals, head.loop_totals)
    assert np.array_equal(back.loop_vertices, head.loop_vertices)
    assert len(obj.data.polygons) == 4220 and len(obj.data.vertices) == 4244


def test_shape_keys_round_trip_through_a_saved_blend(head, tmp_path):
    names = ["jawOpen", "eyeBlink_L", "mouthSmile_L"]
    deltas = smooth_deltas(head.vertices, len(names))
    obj = mesh_io.object_from_mesh("head", head)
    added, replaced, skipped = mesh_io.write_shape_keys(obj, names, deltas)
    assert (added, replaced, skipped) == (names, [], [])
    assert [kb.name for kb in obj.data.shape_keys.key_blocks] == ["Basis"] + names
    # new keys start off: the head still shows its neutral face
    assert [kb.value for kb in obj.data.shape_keys.key_blocks[1:]] == [0.0] * len(names)
    assert np.array_equal(mesh_io.mesh_from_object(obj, evaluated=True,
                                                   depsgraph=bpy.context.evaluated_depsgraph_get()
                                                   ).vertices.astype(np.float32),
                          head.vertices.astype(np.float32))

    path = tmp_path / "head.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    with bpy.data.libraries.load(str(path), link=False) as (data_from, data_to):
        data_to.objects = ["head"]
    loaded = data_to.objects[0]
    read_names, read_deltas = mesh_io.shape_keys_from_object(loaded)
    assert read_names == names
    assert np.array_equal(read_deltas, stored(head.vertices, deltas))
    assert np.array_equal(mesh_io.mesh_from_object(loaded).loop_vertices, head.loop_vertices)


def test_deltas_are_relative_to_the_reference_key_whatever_the_relative_key(head):
    obj = mesh_io.object_from_mesh("head", head)
    deltas = smooth_deltas(head.vertices, 2)
    mesh_io.write_shape_keys(obj, ["a", "b"], deltas)
    key_blocks = obj.data.shape_keys.key_blocks
    key_blocks["b"].relative_key = key_blocks["a"]
    _, read = mesh_io.shape_keys_from_object(obj)
    assert np.array_equal(read[1], stored(head.vertices, deltas[1]))


def test_existing_shape_keys_are_never_overwritten_without_replace_existing(head):
    obj = mesh_io.object_from_mesh("head", head)
    first, second = smooth_deltas(head.vertices, 2)
    mesh_io.write_shape_keys(obj, ["jawOpen"], first[None])
    added, replaced, skipped = mesh_io.write_shape_keys(obj, ["jawOpen", "smile"],
                                                        np.stack([second, second]))
    assert (added, replaced, skipped) == (["smile"], [], ["jawOpen"])
    _, read = mesh_io.shape_keys_from_object(obj)
    assert np.array_equal(read[0], stored(head.vertices, first))
    assert np.array_equal(read[1], stored(head.vertices, second))

    added, replaced, skipped = mesh_io.write_shape_keys(obj, ["jawOpen"], second[None],
                                                        replace_existing=True)
    assert (added, replaced, skipped) == ([], ["jawOpen"], [])
    _, read = mesh_io.shape_keys_from_object(obj)
    assert np.array_equal(read[0], stored(head.vertices, second))


def test_the_basis_key_is_never_written_even_with_replace_existing(head):
    obj = mesh_io.object_from_mesh("head", head)
    delta = smooth_deltas(head.vertices, 1)
    mesh_io.write_shape_keys(obj, ["a"], delta)
    added, replaced, skipped = mesh_io.write_shape_keys(obj, ["Basis"], delta,
                                                        replace_existing=True)
    assert skipped == ["Basis"] and not added and not replaced
    basis = np.empty(len(head.vertices) * 3, np.float32)
    obj.data.shape_keys.key_blocks["Basis"].data.foreach_get("co", basis)
    assert np.array_equal(basis.reshape(-1, 3), head.vertices.astype(np.float32))


def test_wrong_delta_shape_is_refused_before_anything_changes(head):
    obj = mesh_io.object_from_mesh("head", head)
    with pytest.raises(MeshError, match="expected deltas of shape"):
        mesh_io.write_shape_keys(obj, ["a"], np.zeros((1, 10, 3)))
    assert obj.data.shape_keys is None


def test_evaluated_mesh_applies_modifiers_original_does_not(head):
    obj = mesh_io.object_from_mesh("head", head)
    obj.modifiers.new("subdivision", 'SUBSURF').levels = 1
    evaluated = mesh_io.mesh_from_object(obj, evaluated=True,
                                         depsgraph=bpy.context.evaluated_depsgraph_get())
    assert len(evaluated.vertices) > len(head.vertices)
    assert len(mesh_io.mesh_from_object(obj).vertices) == len(head.vertices)


def test_non_mesh_objects_are_refused():
    empty = bpy.data.objects.new("empty", None)
    with pytest.raises(MeshError, match="must be a mesh object"):
        mesh_io.mesh_from_object(empty, what="source")


def test_operator_skips_expressions_that_exist_and_changes_nothing(head):
    """The operator never overwrites shape keys: with every expression already on the target
    it stops before cloning, leaving the keys as they were."""
    from exclone_addon.core.library import load_library
    names = load_library().names
    target = mesh_io.object_from_mesh("head", head)
    deltas = smooth_deltas(head.vertices, len(names))
    mesh_io.write_shape_keys(target, names, deltas)
    bpy.context.view_layer.objects.active = target
    assert bpy.ops.exclone.clone_expressions(use_library=True) == {'CANCELLED'}
    read_names, read = mesh_io.shape_keys_from_object(target)
    assert read_names == names
    assert np.array_equal(read, stored(head.vertices, deltas))


def test_operator_without_a_source_reports_and_changes_nothing(head):
    target = mesh_io.object_from_mesh("head", head)
    bpy.context.view_layer.objects.active = target
    with pytest.raises(RuntimeError, match="Select a source mesh with shape keys"):
        bpy.ops.exclone.clone_expressions()
    assert target.data.shape_keys is None


def test_operator_polls_for_an_active_mesh(head):
    assert not bpy.ops.exclone.clone_expressions.poll()
    target = mesh_io.object_from_mesh("head", head)
    bpy.context.view_layer.objects.active = target
    assert bpy.ops.exclone.clone_expressions.poll()


# -- linked (read-only) data ----------------------------------------------------------------------

def linked_head(head, tmp_path):
    """The head written to a .blend, then linked from it (read-only) into the scene and made
    the active object: (the linked object, the library file)."""
    obj = mesh_io.object_from_mesh("head", head)
    path = tmp_path / "library.blend"
    bpy.data.libraries.write(str(path), {obj})
    mesh = obj.data
    bpy.data.objects.remove(obj)
    bpy.data.meshes.remove(mesh)
    with bpy.data.libraries.load(str(path), link=True) as (_, linked):
        linked.objects = ["head"]
    obj = linked.objects[0]
    bpy.context.scene.collection.objects.link(obj)
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)
    assert obj.library is not None and obj.data.library is not None
    return obj, path


LINKED = r"^'head' is linked from a library \(read-only\): make it local first " \
         r"\(Object > Relations > Make Local\)$"


@pytest.mark.parametrize("operator, options", [("clone_expressions", {"use_library": True}),
                                               ("generate_arkit_shapes", {}),
                                               ("register_faces", {"use_library": True})])
def test_a_linked_target_is_refused_before_any_work(head, tmp_path, operator, options):
    obj, _ = linked_head(head, tmp_path)
    objects = set(bpy.data.objects)
    with pytest.raises(RuntimeError, match=LINKED[1:-1]) as error:
        getattr(bpy.ops.exclone, operator)(**options)
    assert str(error.value).strip().count("\n") == 0, "one line"
    assert obj.data.shape_keys is None and set(bpy.data.objects) == objects
    assert not obj.keys(), "nothing stored on the object"


def test_a_linked_mesh_in_a_target_blend_is_refused_by_the_command_line(head, tmp_path):
    """A .blend whose object 'head' is its own but whose mesh is linked from another file:
    appending the object brings the mesh along still linked, so the keys would be lost."""
    from exclone_addon.blender import files
    from exclone_addon.core.errors import ExCloneError
    linked, _ = linked_head(head, tmp_path)
    mesh = linked.data
    bpy.data.objects.remove(linked)
    bpy.context.scene.collection.objects.link(bpy.data.objects.new("head", mesh))
    scene_file = tmp_path / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(scene_file))
    bpy.ops.wm.read_factory_settings(use_empty=True)
    with pytest.raises(ExCloneError, match=LINKED):
        files.load_target(f"{scene_file}:head")


def test_keep_still_sees_a_head_split_at_a_seam_as_one_part(head):
    """The faces right of the midline on their own copies of its vertices (an exporter's UV
    seam): two pieces, one face. 'Keep Still' holds nothing of it still."""
    from exclone_addon.blender import workflow
    from exclone_addon.core.mesh import PolyMesh, vertex_parts
    v = head.vertices
    midline = np.flatnonzero(np.abs(v[:, 0]) < 1e-9)
    copy_of = dict(zip(midline, len(v) + np.arange(len(midline))))
    faces = [np.array([copy_of.get(i, i) for i in f]) if v[f, 0].mean() > 0 else f
             for f in head.faces()]
    split = PolyMesh.from_faces(np.vstack([v, v[midline]]), faces)
    assert len(np.unique(vertex_parts(len(split.vertices), split.triangles()))) == 2
    left_only = np.flatnonzero(v[:, 0] < -0.1)[:5]
    assert not workflow.still_parts_mask(split, left_only).any()
