"""The artist's workflow through bpy.ops on the bundled demo head and library: landmarks (stored
with the object, markers, snap, mirror), Register (cached, preview), Clone (names, prefix,
no-overwrite, parts), Generate ARKit Shapes, error messages, undo, the panel and registration.

The engine runs several times here (about 6 s each for the library onto the demo head); runs
with unchanged inputs come from the operators' cache, which tests clear where a real run matters.
"""
import json
import re
import time

import bpy
import numpy as np
from scipy.spatial.distance import pdist
import pytest

import exclone_addon
from blender_tests.helpers.paths import REPO_ROOT
from blender_tests.helpers.layout import RecordingLayout
from exclone_addon.core import data
from exclone_addon.blender import landmarks as stored_landmarks
from exclone_addon.blender import mesh_io, operators, panel, preferences, workflow
from exclone_addon.core.errors import Cancelled
from exclone_addon.core.library import ARKIT_BLENDSHAPES, load_library
from exclone_addon.core.mesh import PolyMesh, read_obj

DEMO_HEAD = data.DEMO_HEAD_FILE
# Hand-checked vertices of the demo head (it is the fixture's MakeHuman mesh, same vertex ids).
FIXTURE = json.loads((REPO_ROOT / "blender_tests" / "fixtures" / "makehuman_landmarks.json").read_text())
VERTEX = {name: entry["vertex"] for name, entry in FIXTURE["landmarks"].items()}
OPERATORS = {"auto_landmarks", "clear_landmarks", "clone_expressions", "generate_arkit_shapes",
             "mirror_landmarks", "refresh_expressions", "register_faces", "remove_preview",
             "snap_landmarks"}


@pytest.fixture(scope="module")
def head():
    return read_obj(DEMO_HEAD)


@pytest.fixture(scope="module")
def library():
    return load_library()


def add_object(name, mesh, active=True):
    obj = mesh_io.object_from_mesh(name, mesh)
    if active:
        bpy.context.view_layer.objects.active = obj
        obj.select_set(True)
    return obj


def keys(obj):
    """{name: (n, 3) float64 displacement from the reference key} of every other shape key."""
    names, deltas = mesh_io.shape_keys_from_object(obj)
    return dict(zip(names, deltas))


def reports(capfd):
    """Blender prints operator reports as 'Info: ...' on stdout."""
    return [line[len("Info: "):] for line in capfd.readouterr().out.splitlines()
            if line.startswith("Info: ")]


def lip_parting(head, delta):
    """How far jawOpen parts the lips (upper lip up minus lower lip, file +Y is up), in mouth
    widths."""
    mouth = np.linalg.norm(head.vertices[VERTEX["mouth_corner_left"]]
                           - head.vertices[VERTEX["mouth_corner_right"]])
    return (delta[VERTEX["upper_lip"], 1] - delta[VERTEX["lower_lip"], 1]) / mouth


def head_with_eye(head):
    """The demo head plus a separate UV-sphere eyeball (quads and triangle fans) at the left eye."""
    inner = head.vertices[VERTEX["eye_inner_left"]]
    outer = head.vertices[VERTEX["eye_outer_left"]]
    radius = 0.45 * np.linalg.norm(outer - inner)
    centre = (inner + outer) / 2 - [0, 0, 0.8 * radius]
    rings, segments = 8, 12
    theta = np.linspace(0, np.pi, rings + 1)[1:-1]
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    ring_points = np.stack([np.outer(np.sin(theta), np.cos(phi)), np.outer(np.cos(theta),
                            np.ones_like(phi)), np.outer(np.sin(theta), np.sin(phi))], axis=-1)
    points = np.vstack([[[0, 1, 0]], ring_points.reshape(-1, 3), [[0, -1, 0]]]) * radius + centre
    n = len(head.vertices)
    ring = lambda r, s: n + 1 + r * segments + s % segments  # noqa: E731
    faces = [[n, ring(0, s + 1), ring(0, s)] for s in range(segments)]
    faces += [[ring(r, s), ring(r, s + 1), ring(r + 1, s + 1), ring(r + 1, s)]
              for r in range(rings - 2) for s in range(segments)]
    last = n + len(points) - 1
    faces += [[ring(rings - 2, s), ring(rings - 2, s + 1), last] for s in range(segments)]
    eye = PolyMesh.from_faces(points, faces)
    return PolyMesh(np.vstack([head.vertices, eye.vertices]),
                    np.concatenate([head.loop_totals, eye.loop_totals]),
                    np.concatenate([head.loop_vertices, eye.loop_vertices])), np.arange(n, last + 1)


# -- registration of the add-on -------------------------------------------------------------------

def test_register_unregister_register_is_symmetric():
    exclone_addon.unregister()
    try:
        assert not hasattr(bpy.types.Scene, "exclone")
        assert not any(hasattr(bpy.types, getattr(bpy.ops.exclone, name).idname())
                       for name in OPERATORS)
        assert not hasattr(bpy.types, "EXCLONE_PT_main")
        assert not hasattr(bpy.types, "EXCLONE_AP_preferences")
    finally:
        exclone_addon.register()
    assert OPERATORS <= set(dir(bpy.ops.exclone))
    assert bpy.types.EXCLONE_PT_main.bl_category == "ExClone"
    assert bpy.types.EXCLONE_PT_main.bl_space_type == 'VIEW_3D'
    assert bpy.context.scene.exclone.preset == 'DEFAULT'


def test_every_operator_is_one_undo_step():
    # every operator of this module changes data (keys, landmarks, markers, the preview, the list)
    assert {cls.bl_idname.split(".")[1] for cls in operators.CLASSES} == OPERATORS
    for name in OPERATORS:
        options = getattr(bpy.ops.exclone, name).bl_options
        assert {'REGISTER', 'UNDO'} <= options, name


def test_default_preset_comes_from_the_preferences_once_enabled():
    context = bpy.context
    assert preferences.get(context) is None  # registered by hand, not enabled as an add-on
    assert workflow.clone_settings(context, "DEFAULT", "reduced").preset == "balanced"
    entry = context.preferences.addons.new()
    entry.module = preferences.ADDON_PACKAGE
    prefs = preferences.get(context)
    prefs.default_preset = "precise"
    prefs.camera_index = 2
    assert workflow.clone_settings(context, "DEFAULT", "augmented").preset == "precise"
    assert workflow.clone_settings(context, "fast", "reduced").preset == "fast"


# -- the panel ------------------------------------------------------------------------------------

def draw_panel():
    log = []
    panel.draw(RecordingLayout(log), bpy.context)
    return log


def test_panel_draws_without_and_with_a_selection(head):
    log = draw_panel()
    operators = [entry[1] for entry in log if entry[0] == "operator"]
    for idname in ("exclone.auto_landmarks", "exclone.snap_landmarks", "exclone.register_faces",
                   "exclone.clone_expressions", "exclone.generate_arkit_shapes"):
        assert idname in operators
    assert ("label", "Active: nothing") in log
    assert ("prop", "preset") not in log  # the options section starts collapsed

    add_object("head", head)
    settings = bpy.context.scene.exclone
    settings.show_options = settings.show_expressions = True
    settings.source_mode = 'LIBRARY'
    settings.preset = 'fast'
    log = draw_panel()
    assert ("label", "Active: head") in log
    assert ("label", "Character: 'head' (1 mesh)") in log
    eye = add_object("eye", head, active=False)
    eye.parent = bpy.data.objects["head"]
    assert ("label", "Character: 2 meshes (the face is found among them)") in draw_panel()
    bpy.data.objects.remove(eye)
    assert ("prop", "source") not in log  # the library needs no source object
    for name in ("preset", "formulation", "parts", "prefix", "replace_existing"):
        assert ("prop", name) in log
    assert ("list", "expressions") in log

    bpy.ops.exclone.auto_landmarks()
    count = len(stored_landmarks.stored(bpy.context.active_object))
    assert ("label", f"{count} automatic landmarks on target") in draw_panel()


# -- landmarks ------------------------------------------------------------------------------------

def test_auto_landmarks_are_stored_with_the_object_and_survive_save_and_reload(head, tmp_path):
    obj = add_object("head", head)
    obj.rotation_euler = (np.pi / 2, 0, 0.3)
    obj.scale = (2, 2, 2)
    assert bpy.ops.exclone.auto_landmarks() == {'FINISHED'}
    ids = stored_landmarks.stored(obj)
    # what Clone finds by itself on the target (its found face's head region, with its guide)
    assert (obj, ids) == workflow.target_landmarks(bpy.context)
    assert len(ids) >= 20
    near = np.linalg.norm(head.vertices[ids["nose_tip"]] - head.vertices[VERTEX["nose_tip"]])
    assert near < 0.02 * FIXTURE["bbox_diagonal"]
    markers = stored_landmarks.markers(obj)
    assert set(markers) == set(ids)
    bpy.context.view_layer.update()
    world = np.array(obj.matrix_world)
    for name in ("nose_tip", "chin", "eye_outer_left"):
        on_vertex = world[:3, :3] @ head.vertices[ids[name]] + world[:3, 3]
        assert np.allclose(markers[name].matrix_world.translation, on_vertex, atol=1e-5)
    assert not stored_landmarks.is_edited(obj)

    path = tmp_path / "landmarks.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.wm.open_mainfile(filepath=str(path))
    loaded = bpy.data.objects["head"]
    assert stored_landmarks.stored(loaded) == ids
    assert set(stored_landmarks.markers(loaded)) == set(ids)


def test_snap_and_mirror_edit_landmarks(head):
    obj = add_object("head", head)
    bpy.ops.exclone.auto_landmarks()
    corner = stored_landmarks.markers(obj)["mouth_corner_left"]
    wanted = VERTEX["mouth_corner_left"]          # the hand-checked corner
    others = np.delete(head.vertices, wanted, axis=0)
    spacing = np.linalg.norm(others - head.vertices[wanted], axis=1).min()
    corner.location = head.vertices[wanted] + 0.3 * spacing * np.array([0.6, 0.0, 0.8])  # near it
    with pytest.raises(RuntimeError, match="moved off their vertex .*mouth_corner_left.*"
                                           "press Snap Landmarks"):
        bpy.ops.exclone.clone_expressions(use_library=True)
    assert obj.data.shape_keys is None

    assert bpy.ops.exclone.snap_landmarks() == {'FINISHED'}
    assert stored_landmarks.stored(obj)["mouth_corner_left"] == wanted
    assert np.allclose(corner.location, head.vertices[wanted], atol=1e-6)
    assert stored_landmarks.is_edited(obj)

    assert bpy.ops.exclone.mirror_landmarks(from_side="left") == {'FINISHED'}
    ids = stored_landmarks.stored(obj)
    # The demo head is exactly symmetric: the right corner is the left one's mirror vertex.
    assert ids["mouth_corner_right"] == VERTEX["mouth_corner_right"]
    mirrored = head.vertices[ids["eye_outer_right"]] * [-1, 1, 1]
    assert np.allclose(mirrored, head.vertices[ids["eye_outer_left"]], atol=1e-4)
    assert np.allclose(stored_landmarks.markers(obj)["mouth_corner_right"].location,
                       head.vertices[VERTEX["mouth_corner_right"]], atol=1e-6)

    assert bpy.ops.exclone.clear_landmarks() == {'FINISHED'}
    assert stored_landmarks.IDS not in obj and not stored_landmarks.markers(obj)


def test_auto_landmarks_on_a_non_face_reports_and_changes_nothing():
    bpy.ops.mesh.primitive_cube_add()
    cube = bpy.context.active_object
    objects = len(bpy.data.objects)
    with pytest.raises(RuntimeError, match="Cube: .*(symmetry|landmarks|nose|up direction)"):
        bpy.ops.exclone.auto_landmarks()
    assert stored_landmarks.IDS not in cube and len(bpy.data.objects) == objects


# -- register and clone ---------------------------------------------------------------------------

def test_register_then_clone_library_opens_the_mouth(head, library, capfd):
    workflow.clear_cache()
    obj = add_object("head", head)
    started = time.perf_counter()
    assert bpy.ops.exclone.register_faces(use_library=True) == {'FINISHED'}
    register_seconds = time.perf_counter() - started
    message = reports(capfd)[-1]
    fit = float(re.search(r"fit error ([\d.e-]+)%", message).group(1))
    assert fit < 0.1 and re.search(r"\b\d\d automatic landmarks", message), message
    preview = next(o for o in bpy.data.objects if "exclone_preview" in o)
    assert len(preview.data.vertices) == len(library.mesh.vertices)
    assert np.allclose(np.array(preview.matrix_world), np.array(obj.matrix_world))

    started = time.perf_counter()
    assert bpy.ops.exclone.clone_expressions(use_library=True) == {'FINISHED'}
    clone_seconds = time.perf_counter() - started
    message = reports(capfd)[-1]
    assert re.fullmatch(r"57 shape keys added in [\d.]+ s, fit error [\d.e-]+%; "
                        r"face found on 'head' \(head region: 4,244 of 4,244 vertices\); "
                        r"blink gap L -?\d+% R -?\d+%, stretch [\d.]+x the source's, "
                        r"\d+ flipped, \d+ beyond the source's "
                        r"\(registration reused\)", message), message
    # the panel shows the last run's measures (core.expression_measures)
    labels = [entry[1] for entry in draw_panel() if entry[0] == "label"]
    assert "Last clone: head" in labels
    assert any(re.fullmatch(r"eyeBlink_L: lids -?\d+% open, other \d+%", text) for text in labels)
    assert any(re.fullmatch(r"stretch [\d.]+x the source's", text) for text in labels)
    assert any(re.fullmatch(r"\d+ flipped, \d+ beyond the source's", text) for text in labels)
    # the fit is reused ("registration reused" above): Clone only transfers
    print(f"register {register_seconds:.2f} s, clone after register {clone_seconds:.2f} s")

    cloned = keys(obj)
    assert list(cloned) == library.names
    parting = lip_parting(head, cloned["jawOpen"])
    print(f"jawOpen parts the lips by {parting:.3f} mouth widths")
    assert 0.45 < parting < 0.9  # the library's own face: 0.65
    # The other expressions leave the lips (nearly) closed.
    assert abs(lip_parting(head, cloned["eyeBlink_L"])) < 0.02
    assert bpy.ops.exclone.remove_preview() == {'FINISHED'}
    assert not any("exclone_preview" in o for o in bpy.data.objects)


def test_existing_keys_are_kept_unless_replace_existing(head, capfd):
    obj = add_object("head", head)
    mine = np.full((len(head.vertices), 3), 0.01)
    mesh_io.write_shape_keys(obj, ["jawOpen"], mine[None])
    assert bpy.ops.exclone.clone_expressions(use_library=True) == {'FINISHED'}
    assert "56 shape keys added, 1 skipped (already exist: jawOpen)" in reports(capfd)[-1]
    assert np.allclose(keys(obj)["jawOpen"], mine, atol=1e-6)

    assert bpy.ops.exclone.clone_expressions(use_library=True, prefix="ex_") == {'FINISHED'}
    cloned = keys(obj)
    assert np.allclose(cloned["jawOpen"], mine, atol=1e-6)
    assert lip_parting(head, cloned["ex_jawOpen"]) > 0.45

    assert bpy.ops.exclone.clone_expressions(use_library=True, replace_existing=True) == {'FINISHED'}
    assert "0 shape keys added, 57 replaced" in reports(capfd)[-1]
    assert np.allclose(keys(obj)["jawOpen"], cloned["ex_jawOpen"], atol=1e-6)


# Blender keeps 63 bytes of a name. 60 ASCII characters leave 3 of each expression's name (so
# only expressions whose first 3 letters differ); 60 characters of 64 bytes end in a 2-byte
# character across the cut, which Blender drops with the whole expression name.
LONG_PREFIXES = {"ascii": ("p" * 60, ["jawOpen", "mouthSmile_L", "eyeBlink_L"]),
                 "multi-byte at the cut": ("é" * 3 + "p" * 56 + "é", ["jawOpen"])}


def tick(names):
    settings = bpy.context.scene.exclone
    settings.source_mode = 'LIBRARY'
    assert bpy.ops.exclone.refresh_expressions() == {'FINISHED'}
    for item in settings.expressions:
        item.selected = item.name in names


def test_stored_name_is_the_name_blender_stores(head):
    obj = add_object("head", head)
    obj.shape_key_add(name="Basis")
    names = [prefix + name for prefix, ticked in LONG_PREFIXES.values() for name in ticked]
    for name in names + ["x" * 61 + "€ab", "x" * 62 + "é", "short"]:
        assert obj.shape_key_add(name=name, from_mix=False).name == workflow.stored_name(name)


@pytest.mark.parametrize("prefix,ticked", LONG_PREFIXES.values(), ids=list(LONG_PREFIXES))
def test_a_long_prefix_run_twice_adds_no_duplicates(head, capfd, prefix, ticked):
    obj = add_object("head", head)
    tick(ticked)
    options = dict(only_ticked=True, prefix=prefix, preset="fast")
    assert bpy.ops.exclone.clone_expressions(**options) == {'FINISHED'}
    first = keys(obj)
    assert sorted(first) == sorted(workflow.stored_name(prefix + name) for name in ticked)
    assert bpy.ops.exclone.clone_expressions(**options) == {'CANCELLED'}   # all exist: skipped
    assert list(keys(obj)) == list(first)
    assert bpy.ops.exclone.clone_expressions(replace_existing=True, **options) == {'FINISHED'}
    assert f"0 shape keys added, {len(ticked)} replaced" in reports(capfd)[-1]
    replaced = keys(obj)
    assert list(replaced) == list(first)
    for name, delta in first.items():
        assert np.allclose(replaced[name], delta, atol=1e-6), name


def test_a_prefix_that_cuts_two_names_alike_is_refused(head):
    obj = add_object("head", head)
    tick(["jawOpen", "jawLeft"])
    with pytest.raises(RuntimeError, match="Prefix too long: .*'jaw\\w+' and 'jaw\\w+' would both "
                                           "be named 'p{60}jaw'; use a shorter prefix"):
        bpy.ops.exclone.clone_expressions(only_ticked=True, prefix="p" * 60)
    assert obj.data.shape_keys is None


def test_only_ticked_expressions_are_cloned(head):
    obj = add_object("head", head)
    settings = bpy.context.scene.exclone
    settings.source_mode = 'LIBRARY'
    assert bpy.ops.exclone.refresh_expressions() == {'FINISHED'}
    assert len(settings.expressions) == 57
    for item in settings.expressions:
        item.selected = item.name in ("jawOpen", "mouthSmile_L")
    assert bpy.ops.exclone.clone_expressions(only_ticked=True) == {'FINISHED'}
    assert list(keys(obj)) == ["jawOpen", "mouthSmile_L"]
    for item in settings.expressions:
        item.selected = False
    with pytest.raises(RuntimeError, match="No expression of the source is ticked"):
        bpy.ops.exclone.clone_expressions(only_ticked=True, prefix="x_")


def test_a_mesh_with_shape_keys_is_a_source(head, library, capfd):
    """The source read from an object (its base mesh and keys), named by the object in reports;
    Register then Clone reuses the fit."""
    source = add_object("source", library.mesh, active=False)
    chosen = ["jawOpen", "eyeBlink_L"]
    mesh_io.write_shape_keys(source, chosen, library.subset(chosen).deltas)
    target = add_object("head", head)
    source.select_set(True)
    assert bpy.ops.exclone.refresh_expressions() == {'FINISHED'}
    assert reports(capfd)[-1] == "2 expressions from 'source'"
    assert bpy.ops.exclone.register_faces(preview=False, preset="fast") == {'FINISHED'}
    assert reports(capfd)[-1].startswith("Registered 'source' onto 'head' (head region: "
                                         "4,244 of 4,244 vertices): fit error ")
    assert bpy.ops.exclone.clone_expressions(preset="fast") == {'FINISHED'}
    assert reports(capfd)[-1].endswith("(registration reused)")
    cloned = keys(target)
    assert list(cloned) == chosen and list(keys(source)) == chosen
    assert 0.45 < lip_parting(head, cloned["jawOpen"]) < 0.9


def test_a_source_of_the_targets_base_mesh_is_cloned_vertex_by_vertex(head, capfd):
    """A source object and a target object of one base mesh (here the demo head, the target
    moved, turned and scaled): Register and Clone say so, and the keys are the source's motion,
    turned and scaled with the target."""
    lift = np.zeros_like(head.vertices)
    lift[:, 1] = 0.02 * np.clip(head.vertices[:, 1] - np.median(head.vertices[:, 1]), 0, None)
    source = add_object("source", head, active=False)
    mesh_io.write_shape_keys(source, ["lift"], lift[None])
    target = add_object("target", head)
    target.scale = (2.0, 2.0, 2.0)
    target.rotation_euler = (0.3, 0.0, 0.5)
    source.select_set(True)
    assert bpy.ops.exclone.register_faces(preview=False) == {'FINISHED'}
    message = reports(capfd)[-1]
    assert "the source's own base mesh (4,244 vertices matched, no registration)" in message, \
        message
    assert bpy.ops.exclone.clone_expressions() == {'FINISHED'}
    assert "the source's own base mesh" in reports(capfd)[-1]
    # keys are in the target's own coordinates: the same motion as the source's own keys
    assert np.abs(keys(target)["lift"] - lift).max() < 1e-3 * np.abs(lift).max()


def test_generate_arkit_shapes_gives_apples_names(head, capfd):
    obj = add_object("head", head)
    assert bpy.ops.exclone.generate_arkit_shapes() == {'FINISHED'}
    message = reports(capfd)[-1]
    assert message.startswith("ARKit: 52 shape keys added"), message
    arkit = keys(obj)
    assert list(arkit) == ARKIT_BLENDSHAPES      # tongueOut opens the jaw (core/followers.py)
    bpy.ops.exclone.clone_expressions(use_library=True, prefix="lib_")
    cloned = keys(obj)
    for combined in ("browInnerUp", "cheekPuff"):
        halves = cloned[f"lib_{combined}_L"] + cloned[f"lib_{combined}_R"]
        assert np.allclose(arkit[combined], halves, atol=1e-5)
        assert np.abs(halves).max() > 0.01
    assert np.allclose(arkit["jawOpen"], cloned["lib_jawOpen"], atol=1e-6)


def test_generate_arkit_shapes_brings_a_one_mesh_heads_own_tongue_out(library):
    """An ICT-FaceKit head (the library's own mesh: its tongue is part of the one mesh): tongueOut
    brings the tongue's tip in front of the lips (before, the key was half of the cloned jawOpen
    and the tip stayed 1.6 cm behind them)."""
    obj = add_object("ict", library.mesh)
    assert bpy.ops.exclone.generate_arkit_shapes() == {'FINISHED'}
    tongue_out = keys(obj)["tongueOut"]
    moved = library.mesh.vertices + tongue_out
    names, ids = library.automatic_landmarks
    lips = library.mesh.vertices[[ids[list(names).index(n)] for n in ("upper_lip", "lower_lip")]]
    start, stop = library.parts["face"]
    near_lips = np.linalg.norm(library.mesh.vertices[start:stop] - lips.mean(axis=0), axis=1) < 2.0
    lips_front = moved[start:stop][near_lips, 2].max()          # ICT faces +Z
    start, stop = library.parts["gums_and_tongue"]
    assert moved[start:stop, 2].max() > lips_front + 0.5


def test_edited_landmarks_are_hard_constraints(head, capfd):
    obj = add_object("head", head)
    bpy.ops.exclone.auto_landmarks()
    markers = stored_landmarks.markers(obj)
    automatic = stored_landmarks.stored(obj)["upper_lip"]
    distance = np.linalg.norm(head.vertices - head.vertices[automatic], axis=1)
    distance[automatic] = np.inf
    neighbour = int(np.argmin(distance))
    markers["upper_lip"].location = head.vertices[neighbour]   # the user moves it one vertex
    bpy.ops.exclone.snap_landmarks()
    assert stored_landmarks.is_edited(obj)
    assert bpy.ops.exclone.register_faces(use_library=True, preview=False) == {'FINISHED'}
    message = reports(capfd)[-1]
    count = len(stored_landmarks.stored(obj))
    assert f"{count} edited landmarks" in message, message
    target = workflow.resolve_target(bpy.context, workflow.library_source(), None)
    run = workflow.run_engine(workflow.library_source(), target.face, target.landmarks,
                              workflow.clone_settings(bpy.context, "DEFAULT", "reduced"))
    assert run.cached
    own = target.face.head.own_ids(run.result.target_landmarks)
    assert own.tolist() == list(stored_landmarks.stored(obj).values())
    assert neighbour in own
    # Hard constraints: each landmark of the registered source sits on its target vertex.
    registered = run.result.registered_source[run.result.source_landmarks]
    solved = target.face.head.mesh.vertices[run.result.target_landmarks]
    assert np.abs(registered - solved).max() < 1e-6

    for name in list(markers)[3:]:  # the user deletes all but three
        bpy.data.objects.remove(markers[name])
    bpy.ops.exclone.snap_landmarks()
    assert reports(capfd)[-1].endswith(f"; {len(markers) - 3} without a marker removed")
    with pytest.raises(RuntimeError, match="3 pairs given, at least 4 are needed .*run Auto "
                                           "Landmarks on both"):
        bpy.ops.exclone.clone_expressions(use_library=True)
    assert obj.data.shape_keys is None


def test_rotated_scaled_quad_target_with_keys_and_an_eye(head):
    """Object transforms are applied for the solve (world space) and the keys written back in
    local coordinates: a turned, scaled and moved copy's keys are the engine's world-space
    result turned back through its transform. The target's basis is what is read, its own keys
    stay as they are, quads and the triangle fans of a separate eyeball part are handled; the
    eye follows or keeps still as asked."""
    composite, eye = head_with_eye(head)
    workflow.clear_cache()
    plain = add_object("plain", composite)
    assert bpy.ops.exclone.clone_expressions(use_library=True, preset="fast") == {'FINISHED'}
    expected = keys(plain)

    workflow.clear_cache()  # a real second run, not the cached result
    obj = add_object("moved", composite)
    plain.select_set(False)
    obj.rotation_euler = (0.4, -1.1, 2.0)
    obj.scale = (1.7, 1.7, 1.7)
    obj.location = (5, -2, 1)
    custom = np.zeros_like(composite.vertices)
    custom[:, 0] = 0.3
    mesh_io.write_shape_keys(obj, ["custom"], custom[None])
    obj.data.shape_keys.key_blocks["custom"].value = 1.0   # the evaluated mesh is moved
    obj.active_shape_key_index = 1
    assert bpy.ops.exclone.clone_expressions(use_library=True, preset="fast") == {'FINISHED'}
    cloned = keys(obj)
    assert list(cloned) == ["custom"] + list(expected)
    assert np.allclose(cloned["custom"], custom, atol=1e-6)
    library = workflow.library_source()
    target = workflow.resolve_target(bpy.context, library, None)
    run = workflow.run_engine(library, target.face, target.landmarks,
                              workflow.clone_settings(bpy.context, "fast", "reduced"))
    assert run.cached and target.face_object == obj
    local = workflow.face_object_deltas(obj, target.face, run.result.deltas)
    for name, delta in zip(run.result.names, local):
        assert np.allclose(cloned[name], delta, atol=1e-5), name
    assert 0.45 < lip_parting(composite, cloned["jawOpen"]) < 0.9
    eye_motion = np.linalg.norm(cloned["jawOpen"][eye], axis=1).max()
    jaw_motion = np.linalg.norm(cloned["jawOpen"], axis=1).max()
    print(f"jawOpen moves the eye part {eye_motion / jaw_motion:.3f} x the most moved vertex")
    # the eyeball follows as a rigid body: it keeps its shape in every key
    rest = composite.vertices[eye]
    size = np.ptp(rest, axis=0).max()
    for name in ("jawOpen", "eyeBlink_L", "mouthSmile_L"):
        assert np.allclose(pdist(rest + cloned[name][eye]), pdist(rest), atol=1e-4 * size), name
    # an eyeball stays with the skull, but turns in its eyeLook keys (core/followers.py)
    assert np.abs(cloned["eyeBlink_L"][eye]).max() == 0
    assert np.linalg.norm(cloned["eyeLookIn_L"][eye], axis=1).max() > 0.1 * size

    still = add_object("still", composite)
    obj.select_set(False)
    assert bpy.ops.exclone.clone_expressions(use_library=True, preset="fast",
                                             parts='STILL') == {'FINISHED'}
    kept = keys(still)
    assert all(np.abs(delta[eye]).max() == 0 for delta in kept.values())
    assert np.allclose(kept["jawOpen"][:len(head.vertices)],
                       expected["jawOpen"][:len(head.vertices)], atol=1e-6)


# -- bad input ------------------------------------------------------------------------------------

def test_poll_says_why_an_operator_cannot_run(head):
    for name in ("auto_landmarks", "register_faces", "clone_expressions", "generate_arkit_shapes"):
        with pytest.raises(RuntimeError, match="Nothing selected"):
            getattr(bpy.ops.exclone, name)()
    empty = bpy.data.objects.new("Empty", None)
    bpy.context.scene.collection.objects.link(empty)
    bpy.context.view_layer.objects.active = empty
    with pytest.raises(RuntimeError, match="'Empty' is not a mesh"):
        bpy.ops.exclone.clone_expressions()
    with pytest.raises(RuntimeError, match="no landmarks: run Auto Landmarks"):
        bpy.ops.exclone.snap_landmarks()

    target = add_object("head", head)
    bare = add_object("bare", head, active=False)
    bpy.context.scene.exclone.source = bare
    with pytest.raises(RuntimeError, match="Source 'bare' has no shape keys"):
        bpy.ops.exclone.clone_expressions()
    bpy.context.scene.exclone.source = target
    with pytest.raises(RuntimeError, match="'head' is both source and target"):
        bpy.ops.exclone.register_faces()
    assert target.data.shape_keys is None and bare.data.shape_keys is None


def test_a_stored_landmark_off_the_mesh_is_reported(head):
    obj = add_object("head", head)
    bpy.ops.exclone.auto_landmarks()
    obj[stored_landmarks.IDS]["nose_tip"] = len(head.vertices)    # as typed in Custom Properties
    for operator in (bpy.ops.exclone.clone_expressions, bpy.ops.exclone.register_faces):
        with pytest.raises(RuntimeError, match=r"target 'head' vertex id is outside 0\.\.4243: "
                                               "run Auto Landmarks again"):
            operator(use_library=True)
    assert obj.data.shape_keys is None
    assert not any("exclone_preview" in o for o in bpy.data.objects)


def test_an_internal_error_is_one_line_and_changes_nothing(head):
    """A broken object: its landmarks property is a string, not {name: vertex id} (no operator
    writes one), so plan() raises an AttributeError; the synchronous path reports it as one
    line."""
    obj = add_object("head", head)
    obj[stored_landmarks.IDS] = "not landmarks"
    with pytest.raises(RuntimeError) as error:
        bpy.ops.exclone.clone_expressions(use_library=True)
    message = str(error.value).strip()
    assert re.fullmatch(r"Error: internal error \(AttributeError: [^\n]*\)", message), message
    assert obj.data.shape_keys is None


def test_a_source_object_without_shape_keys_is_refused(head):
    target = add_object("head", head)
    other = add_object("other", head, active=False)
    other.select_set(True)
    bpy.context.view_layer.objects.active = target
    with pytest.raises(RuntimeError, match="Select a source mesh with shape keys"):
        bpy.ops.exclone.register_faces()
    assert not any("exclone_preview" in o for o in bpy.data.objects)


# -- the worker thread behind the UI's modal run (progress, Esc) --------------------------------

def job_inputs(obj, names):
    return (workflow.library_source().subset(names), workflow.basis_mesh(obj, "target"), None,
            workflow.clone_settings(bpy.context, "fast", "reduced"))


def test_a_cancelled_job_stops_and_caches_nothing(head):
    inputs = job_inputs(add_object("head", head), ["jawOpen"])
    workflow.clear_cache()
    job = workflow.EngineJob(*inputs)
    job.cancel()
    job.start()
    assert job.wait(timeout=60)
    assert isinstance(job.error, Cancelled) and job.run is None
    assert not workflow._fits and not workflow._results


def test_a_job_runs_the_engine_in_a_thread_with_progress(head):
    obj = add_object("head", head)
    inputs = job_inputs(obj, ["jawOpen", "eyeBlink_L"])
    workflow.clear_cache()
    job = workflow.EngineJob(*inputs).start()
    seen = set()
    while not job.wait(timeout=0.05):
        seen.add(job.message)
    assert job.error is None and not job.run.cached
    assert (job.fraction, job.message) == (1.0, "done")
    assert len(seen) >= 2, seen   # polled while it ran: the phases went by (registration > 1 s)
    assert 0.45 < lip_parting(head, job.run.result.deltas[0]) < 0.9
    assert workflow.run_engine(*inputs).cached   # the finished job's result is kept


def test_a_register_job_fits_without_transferring(head):
    """Register's inputs end in transfer=False; its job returns the fit alone."""
    inputs = job_inputs(add_object("head", head), ["jawOpen"]) + (False,)
    job = workflow.EngineJob(*inputs).start()
    assert job.wait(timeout=300)
    assert job.error is None, job.error
    assert job.run.result.registered_source.shape == inputs[0].mesh.vertices.shape
    assert not hasattr(job.run.result, "deltas")   # a FaceFit, not a CloneResult


# -- undo -----------------------------------------------------------------------------------------

def test_undo_restores_the_state_before_an_operator(head):
    """In background Blender an operator called from Python pushes no undo step of its own (the
    'UNDO' option acts in the UI), so the steps are pushed by hand around it; undo then takes
    the scene back: everything the operators change is undoable data."""
    add_object("head", head)
    window = bpy.context.window_manager.windows[0]
    with bpy.context.temp_override(window=window):
        bpy.ops.ed.undo_push(message="before")
        bpy.ops.exclone.auto_landmarks()
        bpy.ops.exclone.generate_arkit_shapes()
        bpy.ops.ed.undo_push(message="after")
        assert len(bpy.data.objects) == 27
        bpy.ops.ed.undo()
        obj = bpy.data.objects["head"]
        assert len(bpy.data.objects) == 1 and obj.data.shape_keys is None
        assert stored_landmarks.IDS not in obj
        bpy.ops.ed.redo()
        assert len(keys(bpy.data.objects["head"])) == 52      # with tongueOut
