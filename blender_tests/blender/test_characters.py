"""Real characters as targets (the shared MakeHuman files, as Blender loads them): the operators
find the face's object and head among all the character's objects, in any orientation and
units, solve the head only (nothing below the neck moves), and write world-space results back
in each object's local space. Skipped without the shared data."""
import json
import re

import numpy as np
import pytest

import bpy

from blender_tests.helpers.character_files import load_into_scene
from exclone_addon.blender import character, mesh_io, workflow
from exclone_addon.blender import landmarks as stored_landmarks
from exclone_addon.core.cloning import found_landmarks
from exclone_addon.core.library import arkit_blendshapes
from scripts import batch_clone

# file -> the object the face must be found on
FACE_OBJECT = {
    "mh_male_body.blend": "Body", "mh_male_body.glb": "Body", "mh_female_old_body.fbx": "Body",
    "mh_head_lowpoly.glb": "Head", "mh_head_dense.blend": "Head",
    "mh_stylised_head.blend": "Head", "mh_child_body_expr.blend": "Body",
}
STILL = 1e-4          # x the face object's diagonal: the most a vertex outside the head may move
EXACT = 1e-5          # x the diagonal: world-space key against the engine's delta (float32 keys)
LID_DOWN = 0.05       # eye distances: the least the blinking upper lid comes down
LIP_DOWN = 0.05       # eye distances: the least jawOpen takes the lower lip down


def _select_the_character(objects, face_name):
    """Every mesh selected (the character, where it has no hierarchy) and active an object other
    than the face's (its empty parent, else another mesh): the face must be found from any."""
    for obj in objects.values():
        obj.select_set(obj.type == 'MESH')
    empties = [obj for obj in objects.values() if obj.type == 'EMPTY' and obj.children]
    others = [obj for obj in objects.values() if obj.type == 'MESH' and obj.name != face_name]
    bpy.context.view_layer.objects.active = (empties + others + [objects[face_name]])[0]


def _world_key(obj, name):
    """(n, 3) a shape key's displacement from the basis, in world space."""
    key = obj.data.shape_keys
    count = len(obj.data.vertices)
    co, basis = np.empty(count * 3, np.float32), np.empty(count * 3, np.float32)
    key.key_blocks[name].data.foreach_get("co", co)
    key.reference_key.data.foreach_get("co", basis)
    return (co - basis).reshape(-1, 3).astype(np.float64) @ character.linear_part(obj).T


def _last_report(capfd):
    lines = [line for line in capfd.readouterr().out.splitlines() if line.strip()]
    return lines[-1] if lines else ""


@pytest.mark.parametrize("file_name", sorted(FACE_OBJECT))
def test_generate_arkit_on_a_whole_character(file_name, shared_data, capfd):
    workflow.clear_cache()
    objects = load_into_scene(shared_data / "characters" / file_name)
    face_name = FACE_OBJECT[file_name]
    face_obj = objects[face_name]
    _select_the_character(objects, face_name)
    assert bpy.ops.exclone.generate_arkit_shapes() == {'FINISHED'}
    message = _last_report(capfd)
    region = re.search(rf"face found on '{face_name}' \(head region: ([\d,]+) of ([\d,]+) "
                       r"vertices\)", message)
    assert region, message
    print(f"{file_name}: {message}")

    # the engine's result, reused from its cache: what the keys must show in world space
    context = bpy.context
    target = workflow.resolve_target(context, workflow.library_source(), None)
    assert target.face_object == face_obj
    run = workflow.run_engine(workflow.library_source(), target.face, target.landmarks,
                              workflow.clone_settings(context, "DEFAULT", "reduced"))
    assert run.cached
    names, head_deltas, _ = arkit_blendshapes(run.result.names, run.result.deltas)
    head, guide = target.face.head, target.face.guide
    world = character.world_polymesh(face_obj).vertices
    size = np.linalg.norm(world.max(axis=0) - world.min(axis=0))
    outside = np.setdiff1d(np.arange(len(world)), head.vertex_ids)
    for name in ("jawOpen", "eyeBlink_L", "eyeBlink_R", "mouthSmile_L", "browInnerUp"):
        moved = _world_key(face_obj, name)
        wanted = head.spread(target.face.to_world(head_deltas[names.index(name)][None]))[0]
        assert np.abs(moved - wanted).max() <= EXACT * size, name
        if len(outside):
            assert np.linalg.norm(moved[outside], axis=1).max() < STILL * size, name

    # the face's own axes: up, and the character's left is +X in these files
    left, up = target.face.turn[:, 0], target.face.turn[:, 1]
    assert left[0] > 0.9 and up[2] > 0.9, (left, up)
    # the landmarks the fit used (head numbering), on the face's object
    marks = dict(zip(run.result.landmark_names, head.own_ids(run.result.target_landmarks)))
    lids = {side: marks[f"eyelid_upper_{side}"] for side in ("left", "right")}
    assert world[lids["left"], 0] > world[lids["right"], 0]
    lip = marks["lower_lip"]
    distance = guide.eye_distance
    assert _world_key(face_obj, "jawOpen")[lip] @ up < -LIP_DOWN * distance
    blink = _world_key(face_obj, "eyeBlink_L")
    assert blink[lids["left"]] @ up < 0
    assert blink[lids["left"]] @ up < -LID_DOWN * distance
    assert abs(blink[lids["right"]] @ up) < 0.5 * abs(blink[lids["left"]] @ up)


def test_the_command_line_picks_the_character_of_a_glb(shared_data, tmp_path):
    """A .glb without :Object: the face is found on the body (not the alphabetically first mesh,
    an eyeball), the report says so, and the keys are on the body."""
    out = tmp_path / "male.blend"
    code = batch_clone.main(["--target", str(shared_data / "characters" / "mh_male_body.glb"),
                             "--shapes", "jawOpen,eyeBlink_L", "--no-preview",
                             "--out", str(out)])
    assert code == 0
    report = json.loads(out.with_suffix(".json").read_text())
    assert report["outputs"]["target_object"] == "Body"
    assert re.fullmatch(r"face found on 'Body' \(head region: [\d,]+ of 14,517 vertices\)",
                        report["inputs"]["face"])
    assert report["counts"]["shape_keys_added"] == 2


def test_the_command_line_keys_the_characters_other_objects(shared_data, tmp_path):
    """The CLI gives the eyes, brows, teeth... the face's keys as Clone does (one rule:
    character_keys.follow_character), says so per object in its report, and the .glb it writes
    carries them."""
    out = tmp_path / "male.glb"
    code = batch_clone.main(["--target", str(shared_data / "characters" / "mh_male_body.glb"),
                             "--shapes", "jawOpen,eyeLookOut_L", "--no-preview",
                             "--out", str(out)])
    assert code == 0
    report = json.loads(out.with_suffix(".json").read_text())["outputs"]
    assert report["shape_keys_added"] == ["jawOpen", "eyeLookOut_L"]
    keyed = report["other_object_keys"]
    assert keyed["Teeth"] >= 1 and keyed["Eye_L"] >= 1, keyed
    assert "Teeth" in report["other_objects"]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    objects = load_into_scene(out)
    assert {"jawOpen", "eyeLookOut_L"} <= set(objects["Body"].data.shape_keys.key_blocks.keys())
    teeth_keys = objects["Teeth"].data.shape_keys
    assert teeth_keys is not None and "jawOpen" in teeth_keys.key_blocks
    assert np.abs(_world_key(objects["Teeth"], "jawOpen")).max() > 0.0
    assert "eyeLookOut_L" in objects["Eye_L"].data.shape_keys.key_blocks


def test_auto_landmarks_on_a_body_are_on_its_head(shared_data):
    """Auto Landmarks with the whole body active finds the face as Clone does and places the
    named landmarks on the face's object, inside its head region: the nose tip above the mouth
    corners, in the top 30% of the body's height."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    objects = load_into_scene(shared_data / "characters" / "mh_male_body.blend")
    body = objects["Body"]
    bpy.context.view_layer.objects.active = body
    body.select_set(True)
    assert bpy.ops.exclone.auto_landmarks() == {'FINISHED'}
    ids = {name: int(vertex) for name, vertex in stored_landmarks.stored(body).items()}
    assert {"nose_tip", "mouth_corner_left", "mouth_corner_right"} <= set(ids)
    face = workflow.character_face(character.parts([body]))
    assert set(ids.values()) <= set(face.head.vertex_ids.tolist())
    world = character.world_mesh(body).vertices
    up = np.array([0.0, 0.0, 1.0])       # the MakeHuman body stands upright along +Z
    corners = world[[ids["mouth_corner_left"], ids["mouth_corner_right"]]] @ up
    assert world[ids["nose_tip"]] @ up > corners.max()
    assert world[ids["nose_tip"]] @ up > world[:, 2].max() - 0.3 * np.ptp(world[:, 2])


# The automatic landmarks Clone uses on a found face against FaceMesh's points of the same name,
# across the face (eye distances). Measured on the realistic heads: 0.01-0.14, the alar creases
# 0.2 (placed a little differently). The stylised head's alar creases were 0.5 away (beside its
# mouth), its upper lip 0.32 and mouth corners 0.18: its lips stand out further than its nose,
# so the geometric walk started on them.
AGREE_WITH_FACEMESH = {"nose_tip": 0.25, "subnasal": 0.25, "upper_lip": 0.25, "lower_lip": 0.25,
                       "alar_left": 0.25, "alar_right": 0.25, "mouth_corner_left": 0.12,
                       "mouth_corner_right": 0.12}


@pytest.mark.parametrize("file_name", sorted(FACE_OBJECT))
def test_automatic_landmarks_agree_with_the_face_models(file_name, shared_data):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    obj = load_into_scene(shared_data / "characters" / file_name)[FACE_OBJECT[file_name]]
    face = workflow.character_face(character.parts([obj]))
    names, ids = found_landmarks(face.head.mesh, "target", face_guide=face.guide)
    across = face.guide.frame.rotation[:, :2]
    apart = {name: np.linalg.norm((face.head.mesh.vertices[i] - face.guide.points[name]) @ across)
             / face.guide.eye_distance for name, i in zip(names, ids)
             if name in AGREE_WITH_FACEMESH and name in face.guide.points}
    assert set(apart) == set(AGREE_WITH_FACEMESH) & set(face.guide.points)
    assert all(apart[name] <= AGREE_WITH_FACEMESH[name] for name in apart), apart


def _make_active(obj):
    for one in bpy.context.selected_objects:
        one.select_set(False)
    obj.select_set(True)
    bpy.context.view_layer.objects.active = obj


def test_landmark_edits_reach_the_face_object_whatever_is_active(shared_data):
    """Auto Landmarks stores a character's landmarks on its face's object. Snap, Mirror and
    Clear act on them with the dragged marker, an eye or the character's parent active (they
    were greyed out with "no landmarks: run Auto Landmarks")."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    objects = load_into_scene(shared_data / "characters" / "mh_male_body.blend")
    body = objects["Body"]
    _make_active(body)
    assert bpy.ops.exclone.auto_landmarks() == {'FINISHED'}
    corner = stored_landmarks.stored(body)["mouth_corner_left"]
    local = mesh_io.mesh_from_object(body).vertices       # marker locations are the body's local
    wanted = int(np.argsort(np.linalg.norm(local - local[corner], axis=1))[3])    # a near vertex
    marker = stored_landmarks.markers(body)["mouth_corner_left"]
    marker.location = local[wanted]

    _make_active(marker)                   # as after dragging it
    assert bpy.ops.exclone.snap_landmarks() == {'FINISHED'}
    assert stored_landmarks.stored(body)["mouth_corner_left"] == wanted

    _make_active(objects["Eye_L"])
    assert bpy.ops.exclone.mirror_landmarks(from_side="left") == {'FINISHED'}
    ids = stored_landmarks.stored(body)
    world = character.world_mesh(body).vertices
    mirror = world[ids["mouth_corner_left"]] * [-1.0, 1.0, 1.0]   # the body's plane is x = 0
    spacing = np.linalg.norm(world[wanted] - world[corner])
    assert np.linalg.norm(world[ids["mouth_corner_right"]] - mirror) <= 2 * spacing

    _make_active(objects["mh_male_body"])  # the character's empty parent
    assert bpy.ops.exclone.clear_landmarks() == {'FINISHED'}
    assert stored_landmarks.IDS not in body and not stored_landmarks.markers(body)


def test_the_face_is_found_off_the_main_thread_before_the_operator_plans(shared_data):
    """From the UI the engine operators find the face in a worker (FaceSearch) before plan()
    runs on the main thread: the search covers exactly the face plan() then uses (the same
    object, remembered), for the library and for a character as the source object."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    objects = load_into_scene(shared_data / "characters" / "mh_male_body.blend")
    before = set(bpy.data.objects)
    load_into_scene(shared_data / "characters" / "mh_child_body_expr.blend")
    source, = [obj for obj in bpy.data.objects if obj not in before and obj.name.startswith("Body")]
    _select_the_character(objects, "Body")
    source.select_set(True)
    workflow.clear_cache()
    context = bpy.context
    for use_library in (True, False):
        searches = workflow.face_searches(context, use_library)
        assert len(searches) == (1 if use_library else 2)
        assert workflow.FaceSearch(searches).start().wait(timeout=300)
        found = [workflow.character_face(parts) for parts in searches]
        library_or_body, source_obj = workflow.resolve_source(
            context, workflow.target_object(context), use_library)
        target = workflow.resolve_target(context, library_or_body, source_obj)
        assert target.face is found[-1]
        assert objects[FACE_OBJECT["mh_male_body.blend"]] is target.face_object
        if not use_library:
            assert source_obj is source


def test_edited_source_landmarks_pair_with_the_bodys_head(shared_data):
    """Landmarks edited on the source only: the body's side is found as Clone finds it (on its
    head region), so the pairs hold (the whole-body path found 1 landmark and failed)."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    body = load_into_scene(shared_data / "characters" / "mh_male_body.blend")["Body"]
    source = workflow.library_source()
    source_obj = mesh_io.object_from_mesh("source", source.mesh)
    automatic = dict(zip(source.automatic_landmarks[0],
                         (int(i) for i in source.automatic_landmarks[1])))
    stored_landmarks.store(source_obj, automatic, automatic=True)
    edited = dict(automatic, nose_tip=int(source.mesh.triangles()[0][0]))
    stored_landmarks.store(source_obj, edited, automatic=False)
    target = workflow.target_of([body], source, source_obj)
    assert target.face_object is body and target.face.guide is not None
    assert len(target.landmarks["target"]) >= 10
    assert max(target.landmarks["target"]) < len(target.face.head.vertex_ids)   # head numbering
