"""A full MakeHuman character (shared data): its head cloned with the library, then its eyes,
eyebrows, eyelashes, teeth and tongue get the same keys (core/followers.py,
blender/character_keys.py), driven by the face's keys and removable with them.

The head is cut out of the body above the neck and cloned with the engine; the body's keys carry
the head's motion (nothing below the cut moves)."""
import bpy
import numpy as np
import pytest
from scipy.spatial.distance import pdist
from scipy.spatial.transform import Rotation

from exclone_addon.blender import character, character_keys, mesh_io
from exclone_addon.core import data, followers
from exclone_addon.core.cloning import clone_expressions, found_landmarks
from exclone_addon.core.library import arkit_blendshapes, load_library
from exclone_addon.core.mesh import PolyMesh

WANTED = ["eyeLookIn_L", "eyeLookOut_L", "eyeLookUp_L", "eyeLookDown_L", "eyeBlink_L",
          "browInnerUp_L", "browInnerUp_R", "jawOpen", "mouthSmile_L"]
NECK = 1.60          # metres: the male body's neck lies below, the whole head above
LASHES_ALONG = 0.95   # the lashes' mean motion against the lid's at their bases: cosine
LASHES_AS_FAR = (0.8, 1.5)   # and its size, x the lid's: the tips swing out of the turning lid


def head_cut(vertices, triangles, height):
    """(PolyMesh of the triangles wholly above `height`, their vertex ids in the body)."""
    kept = triangles[(vertices[triangles][:, :, 2] > height).all(axis=1)]
    ids = np.unique(kept)
    return PolyMesh.from_faces(vertices[ids], np.searchsorted(ids, kept).tolist()), ids


def opened(shared_data):
    """The male body's file opened; its Body object."""
    bpy.ops.wm.open_mainfile(filepath=str(shared_data / "characters" / "mh_male_body.blend"))
    return bpy.data.objects["Body"]


@pytest.fixture(scope="module")
def clone(shared_data):
    """The male body's head cloned with the library: (names, world deltas of the Body, face
    points)."""
    body = opened(shared_data)
    world = character.world_mesh(body)
    head, ids = head_cut(world.vertices, world.triangles, NECK)
    library = load_library()
    sub = library.subset(WANTED)
    result = clone_expressions(sub.mesh, sub.deltas, sub.names, head,
                               source_landmarks=library.automatic_landmarks,
                               source_modes=library.shape_modes)
    names, head_deltas, _ = arkit_blendshapes(result.names, result.deltas)
    deltas = np.zeros((len(names), len(world.vertices), 3))
    deltas[:, ids] = head_deltas
    points = character_keys.skin_points(world.vertices, world.triangles, result.landmark_names,
                                        ids[result.target_landmarks])
    return names, deltas, points


def keyed(shared_data, clone):
    """The file opened again, the Body given the clone's keys and the followers theirs: (Body,
    [(object names, kinds, key count)])."""
    names, deltas, points = clone
    body = opened(shared_data)
    mesh_io.write_shape_keys(body, names, character.local_deltas(body, deltas))
    skin = tuple(character.world_mesh(body))
    return body, character_keys.follow_face(body, names, skin, deltas, points,
                                             character.character_objects(body)[1:])


@pytest.fixture(scope="module")
def male(shared_data, clone):
    """Every follower's keys and rest positions read back from Blender, and the face."""
    names, deltas, points = clone
    body, done = keyed(shared_data, clone)
    world = character.world_mesh(body)
    objects = [obj for obj in bpy.data.objects if obj.type == 'MESH']
    return {"names": names, "deltas": deltas, "done": done,
            "face": followers.face_from_points(world.vertices, world.triangles, points),
            "keys": {obj.name: keys(obj) for obj in objects if obj.data.shape_keys},
            "rest": {obj.name: character.world_mesh(obj).vertices for obj in objects}}


def keys(obj):
    """{name: (n, 3) local displacement} of the object's keys."""
    reference = coordinates(obj.data.shape_keys.reference_key)
    return {block.name: coordinates(block) - reference
            for block in obj.data.shape_keys.key_blocks[1:]}


def coordinates(block):
    co = np.empty(len(block.data) * 3, dtype=np.float32)
    block.data.foreach_get("co", co)
    return co.reshape(-1, 3).astype(np.float64)


def test_every_follower_gets_its_keys(male):
    print("followers:", character_keys.summary(male["done"]))
    got = {name: (kinds, count) for name, kinds, count in male["done"]}
    assert got["Eye_L"] == (["eye"], 4) and "Eye_R" not in got     # only the left eye's keys
    assert got["Teeth"][0] == ["teeth"] and got["Tongue"][0] == ["tongue"]
    assert sorted(male["keys"]["Eye_L"]) == sorted(
        ["eyeLookIn_L", "eyeLookOut_L", "eyeLookUp_L", "eyeLookDown_L"])
    assert {"Eyebrows", "Eyelashes", "Teeth", "Tongue"} <= set(got)
    assert {"jawOpen", "tongueOut"} <= set(male["keys"]["Teeth"])
    assert "eyeBlink_L" in male["keys"]["Eyelashes"]


def test_eye_turns_in_towards_the_nose_by_the_stated_angle(male):
    eye = male["rest"]["Eye_L"]
    turned = eye + male["keys"]["Eye_L"]["eyeLookIn_L"]
    rotation = Rotation.align_vectors(turned - turned.mean(axis=0), eye - eye.mean(axis=0))[0]
    angle = np.degrees(rotation.magnitude())
    print(f"eyeLookIn_L: the left eye turns {angle:.2f} degrees")
    assert abs(angle - followers.EYE_LOOK_DEGREES["In"]) < 1
    gaze = rotation.apply(male["face"].forward)
    assert gaze @ male["face"].left < -0.4          # the left eye looks towards the nose
    centre = followers._fitted_sphere(eye)[0]
    assert np.linalg.norm(rotation.apply(eye - centre) + centre - turned, axis=1).max() < 1e-6


def test_lashes_close_with_the_lid(male):
    """The lashes above the left eye come down with the lid margin their bases sit on: the
    same way, and as far or (their tips standing out of the turning lid) a little further. The
    lid rolls down and back over the eye (at the lashes' bases 6.2 mm down, 2.3 mm back since
    the registration starts from the library's nearest face; 6.6 mm and 0.1 mm before), and the
    lashes swing with it (7.9 mm down: 1.25x the bases' motion; 0.95x before)."""
    face, names, deltas = male["face"], male["names"], male["deltas"]
    lashes = male["rest"]["Eyelashes"]
    eye_centre = followers._fitted_sphere(male["rest"]["Eye_L"])[0]
    above_left = ((lashes - eye_centre) @ face.up > 0) & ((lashes - face.mouth) @ face.left > 0)
    lash_motion = male["keys"]["Eyelashes"]["eyeBlink_L"][above_left].mean(axis=0)
    _, triangle, distance, bary = face.skin.closest(lashes[above_left])
    base = distance <= distance.min() + followers.ROOT_GAP * face.span
    corners = face.skin.triangles[triangle[base]]
    lid = np.einsum("mc,mcx->mx", bary[base],
                    deltas[names.index("eyeBlink_L")][corners]).mean(axis=0)
    print(f"eyeBlink_L: lashes above the left eye move {1000 * lash_motion.round(5)} mm, the lid "
          f"at their bases {1000 * lid.round(5)} mm")
    assert lid @ face.up < -0.02 * face.span                       # the lid comes down
    size = np.linalg.norm(lid)
    assert lash_motion @ lid >= LASHES_ALONG * size * np.linalg.norm(lash_motion)
    assert LASHES_AS_FAR[0] * size <= np.linalg.norm(lash_motion) <= LASHES_AS_FAR[1] * size


def test_brows_rise_with_browInnerUp(male):
    face = male["face"]
    rise = male["keys"]["Eyebrows"]["browInnerUp"] @ face.up
    print(f"browInnerUp lifts the eyebrows by up to {rise.max() * 1000:.1f} mm")
    assert rise.max() > 0.02 * face.span and rise.min() > -0.005 * face.span


def test_lower_teeth_move_with_the_jaw_upper_teeth_stay(male):
    face = male["face"]
    teeth = male["rest"]["Teeth"]
    motion = male["keys"]["Teeth"]["jawOpen"]
    moving = np.linalg.norm(motion, axis=1) > 0
    assert 0.3 < moving.mean() < 0.7                                # one row of two
    assert (motion[moving] @ face.up).mean() < -0.05 * face.span     # down with the chin
    assert np.abs(motion[~moving]).max() == 0                        # the upper row stays
    lower = teeth[moving]
    assert np.allclose(pdist(lower + motion[moving]), pdist(lower), atol=1e-6)
    assert (teeth[~moving] @ face.up).mean() > (lower @ face.up).mean()


def test_tongue_comes_out_beyond_the_lips(male):
    face, names, deltas = male["face"], male["names"], male["deltas"]
    tongue = male["rest"]["Tongue"]
    moved = tongue + male["keys"]["Tongue"]["tongueOut"]
    near = np.linalg.norm(face.skin.vertices - face.mouth, axis=1) < 0.3 * face.span
    lips = face.skin.vertices[near] + deltas[names.index("tongueOut")][near]
    lips_front = (lips @ face.forward).max()
    tip = (moved @ face.forward).max()
    print(f"tongueOut: the tip stands {1000 * (tip - lips_front):.1f} mm in front of the lips")
    assert tip > lips_front + 0.1 * face.span
    assert (tongue @ face.forward).max() < lips_front                 # it starts inside


def test_follower_keys_are_driven_and_removed_with_the_face_keys(shared_data, clone):
    body, _ = keyed(shared_data, clone)
    teeth = bpy.data.objects["Teeth"]
    body.data.shape_keys.key_blocks["jawOpen"].value = 0.7
    bpy.context.view_layer.update()
    assert teeth.data.shape_keys.key_blocks["jawOpen"].value == pytest.approx(0.7)
    mesh_io.write_shape_keys(teeth, ["mine"], np.zeros((1, len(teeth.data.vertices), 3)))
    bpy.context.view_layer.objects.active = body
    assert bpy.ops.exclone.remove_keys() == {'FINISHED'}
    assert [block.name for block in teeth.data.shape_keys.key_blocks] == ["Basis", "mine"]
    assert [block.name for block in body.data.shape_keys.key_blocks] == ["Basis"]
    assert bpy.data.objects["Eye_L"].data.shape_keys is None
    animation = teeth.data.shape_keys.animation_data
    assert animation is None or not animation.drivers


def test_brows_and_lashes_follow_as_makehuman_refits_them(shared_data):
    """mh_child_body_expr carries MakeHuman's own expression units on the body and its refit of
    the eyebrows and eyelashes: driven by the body's keys, the followers move them alike."""
    bpy.ops.wm.open_mainfile(filepath=str(shared_data / "characters" / "mh_child_body_expr.blend"))
    body = bpy.data.objects["Body"]
    world = character.world_mesh(body)
    head, ids = head_cut(world.vertices, world.triangles, 0.90)
    names, found = found_landmarks(head)
    points = character_keys.skin_points(world.vertices, world.triangles, names, ids[found])
    face = followers.face_from_points(world.vertices, world.triangles, points)
    body_keys = keys(body)
    expressions = list(body_keys)
    objects = [bpy.data.objects["Eyebrows"], bpy.data.objects["Eyelashes"]]
    followings = followers.follow(face, np.stack([body_keys[name] for name in expressions]),
                                  expressions, [tuple(character.world_mesh(obj)) for obj in objects])
    for obj, following in zip(objects, followings):
        for name, reference in keys(obj).items():
            ours = following.deltas[expressions.index(name)]
            moving = np.linalg.norm(reference, axis=1) > 1e-4
            error = np.linalg.norm(ours - reference, axis=1)[moving].mean() \
                / np.linalg.norm(reference, axis=1)[moving].mean()
            cosine = (ours[moving] * reference[moving]).sum() \
                / np.linalg.norm(ours[moving]) / np.linalg.norm(reference[moving])
            print(f"{obj.name} {name}: mean error {error:.0%} of MakeHuman's motion, "
                  f"direction cosine {cosine:.3f}")
            if obj.name == "Eyebrows":
                assert error < 0.2 and cosine > 0.98, name
            else:
                assert error < 0.5 and cosine > 0.9, name
    # one object with both eyes, the teeth's two rows with their gums, the tongue
    eyes, teeth, tongue = followers.follow(
        face, np.zeros((1, len(world.vertices), 3)), ["jawOpen"],
        [tuple(character.world_mesh(bpy.data.objects[name])) for name in ("Eyes", "Teeth", "Tongue")])
    assert sorted(piece.side for piece in eyes.pieces if piece.kind == followers.EYE) == [0, 1]
    roles = np.concatenate([piece.roles for piece in teeth.pieces])
    assert teeth.kinds() == ["teeth"] and 0.3 < np.mean(roles == followers.LOWER) < 0.7
    assert tongue.kinds() == ["tongue"]


def test_generate_arkit_shapes_keys_the_whole_character(shared_data, capfd):
    """Generate ARKit Shapes on the male body: 52 of 52 names on the body, the followers' keys
    listed per object in its report, each driven by the body's key."""
    body = opened(shared_data)
    bpy.context.view_layer.objects.active = body
    assert bpy.ops.exclone.generate_arkit_shapes(preset="fast") == {'FINISHED'}
    message = [line for line in capfd.readouterr().out.splitlines()
               if line.startswith("Info: ARKit")][-1]
    print(message)
    assert "52 of 52 ARKit shapes" in message and "no tongue" not in message
    for name in ("Eye_L", "Eye_R", "Eyebrows", "Eyelashes", "Teeth", "Tongue"):
        assert name in message, name
    eye_keys = [block.name for block in bpy.data.objects["Eye_R"].data.shape_keys.key_blocks]
    assert sorted(eye_keys[1:]) == sorted(f"eyeLook{d}_R" for d in ("Up", "Down", "In", "Out"))
    tongue = bpy.data.objects["Tongue"].data.shape_keys
    assert {"jawOpen", "tongueOut"} <= set(tongue.key_blocks.keys())
    driven = {fcurve.data_path for fcurve in tongue.animation_data.drivers}
    assert 'key_blocks["tongueOut"].value' in driven


def test_remove_exclone_keys_on_a_lone_head_keeps_the_users_keys():
    """A head without other objects: Remove ExClone Keys takes Generate ARKit's 52 keys (one
    undo step) and leaves a key of the user's."""
    obj = mesh_io.object_from_mesh("head", data.demo_head())
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)
    mesh_io.write_shape_keys(obj, ["mine"], np.zeros((1, len(obj.data.vertices), 3)))
    assert bpy.ops.exclone.generate_arkit_shapes(preset="fast") == {'FINISHED'}
    assert len(obj.data.shape_keys.key_blocks) == 2 + 52
    assert bpy.ops.exclone.remove_keys() == {'FINISHED'}
    assert [block.name for block in obj.data.shape_keys.key_blocks] == ["Basis", "mine"]
    with pytest.raises(RuntimeError, match="ExClone made no keys"):
        bpy.ops.exclone.remove_keys()
