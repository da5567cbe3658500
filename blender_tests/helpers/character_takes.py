"""A rendered take of a MakeHuman character (../shared/data/characters) wearing the ARKit keys
Clone gives it (scripts/batch_clone.py), to be tracked onto that character as a user's avatar: a
face neither the tracker model nor the appearance map was learnt from (MakeHuman's topology, look
and proportions; the expressions ICT's, cloned). Posed and turned as takes.take_recipe's takes,
rendered by scripts/render_faces.py and cached on disk by the recipe and the cloned character.
Or a character wearing its own keys (OWN_KEYS_CHARACTER: MakeHuman's expression units, no ARKit
name among them), each key rising and falling twice while the head turns as in those takes.
"""
import functools
import hashlib
import sys
import tempfile
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from exclone_addon.core.retarget import AvatarRig
from exclone_addon.core.tracking import FRONTAL, Camera
from blender_tests.helpers.character_files import load_into_scene
from blender_tests.helpers.frame_cache import cached_frames
from blender_tests.helpers.paths import REPO_ROOT, SHARED_DATA
from blender_tests.helpers.takes import (BUMP_FRAMES, BUMP_SPACING, DRIVEN, IMAGE_SIZE,
                                         RENDER_DISTANCE_CM, calibration_length, render_frames,
                                         take_recipe, track_rendered, unit_keys)

sys.path.insert(0, str(REPO_ROOT / "scripts"))   # batch_clone, render_faces

CHARACTER = "mh_male_body.blend"
OWN_KEYS_CHARACTER = "mh_child_body_expr.blend"
CHARACTER_CACHE = Path(tempfile.gettempdir()) / "exclone_character_takes"
# Blender's world (Z up, the character facing -Y, metres) -> the renders' model space (+Y up,
# facing +Z, centimetres as the ICT head's)
TO_MODEL = 100.0 * np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


@functools.lru_cache(maxsize=2)
def cloned_character(file_name=CHARACTER, shapes=None):
    """The character (a file of ../shared/data/characters whose body is named Body) with the
    bundled library's expressions (or those named in `shapes`, comma-separated) cloned onto it
    by the command line, read back: its meshes in model space ([(name, vertices, triangles,
    {key: deltas})], the body first), the body's key names and its AvatarRig (the tracker's
    points located on the body as a take locates them on an avatar), with the located points in
    model space."""
    import batch_clone
    with tempfile.TemporaryDirectory(prefix="exclone_character_") as folder:
        out = Path(folder) / "character.blend"
        code = batch_clone.main(["--target", str(SHARED_DATA / "characters" / file_name),
                                 "--no-preview", "--out", str(out)]
                                + (["--shapes", shapes] if shapes else []))
        if code != 0:
            raise RuntimeError(f"batch_clone exited with {code}")
        return _read_character(out)


@functools.lru_cache(maxsize=1)
def own_keys_character(file_name=OWN_KEYS_CHARACTER):
    """A character of ../shared/data/characters with its own keys, read as cloned_character's
    (nothing cloned)."""
    return _read_character(SHARED_DATA / "characters" / file_name)


def _read_character(path):
    import bpy
    bpy.ops.wm.read_factory_settings(use_empty=True)
    objects = load_into_scene(path)
    meshes = [_mesh_arrays(objects["Body"])]
    meshes += [_mesh_arrays(obj) for name, obj in sorted(objects.items())
               if obj.type == 'MESH' and name != "Body"]
    body = objects["Body"]
    names = list(body.data.shape_keys.key_blocks.keys())[1:]
    local, triangles, keys = _local_arrays(body)
    rig = AvatarRig.from_arrays(local, triangles, np.array([keys[n] for n in names]), names)
    located = _to_model(body, rig.neutral)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return SimpleNamespace(meshes=meshes, names=names, rig=rig, located=located)


def _local_arrays(obj):
    """(basis vertices (n, 3), triangles (t, 3), {key name: deltas (n, 3)}) in the object's own
    coordinates."""
    mesh = obj.data
    n = len(mesh.vertices)
    keys = mesh.shape_keys.key_blocks if mesh.shape_keys else []
    basis = np.empty(3 * n)
    (keys[0].data if keys else mesh.vertices).foreach_get("co", basis)
    basis = basis.reshape(-1, 3)
    deltas = {}
    for key in list(keys)[1:]:
        co = np.empty(3 * n)
        key.data.foreach_get("co", co)
        deltas[key.name] = co.reshape(-1, 3) - basis
    mesh.calc_loop_triangles()
    triangles = np.empty(3 * len(mesh.loop_triangles), dtype=np.int64)
    mesh.loop_triangles.foreach_get("vertices", triangles)
    return basis, triangles.reshape(-1, 3), deltas


def _to_model(obj, points, displacement=False):
    """Points (or displacements) in obj's own coordinates -> model space."""
    matrix = np.array(obj.matrix_world)
    world = np.asarray(points) @ matrix[:3, :3].T + (0.0 if displacement else matrix[:3, 3])
    return world @ TO_MODEL.T


def _mesh_arrays(obj):
    basis, triangles, deltas = _local_arrays(obj)
    return (obj.name, _to_model(obj, basis), triangles,
            {name: _to_model(obj, d, displacement=True) for name, d in deltas.items()})


def rendered_character_take(kind="moving"):
    """The character's take (takes.take_recipe's `kind`, the small calibration), rendered: as
    takes.rendered_take's, with avatar (the character's AvatarRig)."""
    character = cloned_character(CHARACTER, None)
    weights, angles = take_recipe(kind)
    names = character.names
    truth = np.zeros((len(weights), len(names)))
    for u, unit in enumerate(DRIVEN):
        truth[:, unit_keys(names, unit)] = weights[:, u:u + 1]
    take = _rendered(character, CHARACTER, kind, truth, angles)
    take.unit_weights = weights
    return take


def rendered_own_keys_take(kind="moving"):
    """OWN_KEYS_CHARACTER's take wearing its own keys: each key in a bump (takes.BUMP_FRAMES
    long, 0.6-1 at its peak) every takes.BUMP_SPACING frames, all of them in turn and then again
    (none for "turning"), the head turning as take_recipe's `kind` (the small calibration);
    rendered, as rendered_character_take's but with no unit_weights."""
    character = own_keys_character()
    names = character.names
    calibration = calibration_length()
    frames = calibration + 2 * BUMP_SPACING * len(names) + BUMP_FRAMES
    _, angles = take_recipe(kind, frames)
    truth = np.zeros((frames, len(names)))
    if kind != "turning":
        rng = np.random.default_rng(5)
        bump = 0.5 - 0.5 * np.cos(2 * np.pi * np.arange(BUMP_FRAMES) / (BUMP_FRAMES - 1))
        for slot, key in enumerate(list(range(len(names))) * 2):
            start = calibration + BUMP_SPACING * slot
            truth[start:start + BUMP_FRAMES, key] = rng.uniform(0.6, 1.0) * bump
    return _rendered(character, OWN_KEYS_CHARACTER, kind, truth, angles)


def tracked_take_fixtures(render):
    """Module fixtures named moving, still and turning: that kind of take, rendered by
    `render(kind)` (rendered_character_take or rendered_own_keys_take), and its frames tracked
    onto the character as its avatar ((take, tracked): takes.track_rendered)."""
    def fixture(kind):
        @pytest.fixture(scope="module", name=kind)
        def tracked(shared_data):
            take = render(kind)
            return take, track_rendered(take, avatar=take.avatar)
        return tracked
    return tuple(fixture(kind) for kind in ("moving", "still", "turning"))


def _rendered(character, file_name, kind, truth, angles):
    """The character's take wearing the weights `truth` (T, N) of its keys, the head turned by
    `angles` (T, 3: yxz Euler degrees, camera axes), rendered and cached."""
    names = character.names
    rotations = Rotation.from_euler("yxz", angles, degrees=True) * FRONTAL
    translation = np.array([0.0, 0.0, RENDER_DISTANCE_CM])
    centre = character.located.mean(axis=0)
    vertices = np.vstack([vertices for _, vertices, _, _ in character.meshes])
    deltas = np.concatenate([[keys.get(name, np.zeros_like(v)) for name in names]
                             for _, v, _, keys in character.meshes], axis=1)
    # the key holds everything the frames are made of: a recipe changed renders them again
    digest = hashlib.sha1(b"".join(np.ascontiguousarray(part).tobytes() for part in (
        vertices, deltas, truth, rotations.as_quat()))).hexdigest()[:12]
    key = f"{file_name}-{kind}-{len(truth)}-{IMAGE_SIZE}-{RENDER_DISTANCE_CM}-{digest}"
    paths, seconds = cached_frames(
        CHARACTER_CACHE / hashlib.sha1(key.encode()).hexdigest()[:16], len(truth),
        lambda paths: _render(paths, character, vertices, deltas, truth, rotations,
                              translation, centre))
    return SimpleNamespace(frames=paths, truth=truth, names=names,
                           rotations=rotations, translation=translation, kind=kind,
                           camera=Camera.from_image_size(*IMAGE_SIZE), render_s=seconds,
                           calibration_frames=calibration_length(), avatar=character.rig)


def _render(paths, character, vertices, deltas, truth, rotations, translation, centre):
    import render_faces      # needs bpy
    offsets = np.cumsum([0] + [len(v) for _, v, _, _ in character.meshes])
    triangles = np.vstack([t + offset for (_, _, t, _), offset in zip(character.meshes, offsets)])
    colours = render_faces.character_colours([(name, v) for name, v, _, _ in character.meshes],
                                             character.located)
    renderer = render_faces.FaceRenderer(triangles, colours, IMAGE_SIZE)
    return render_frames(renderer, paths, vertices, deltas, truth, rotations, translation, centre)
