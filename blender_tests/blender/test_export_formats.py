"""scripts/batch_clone.py --out x.glb / x.fbx: the target with its new shape keys written through
Blender's own exporters. Each file is imported back into an empty scene and every key must move
every vertex as in the .blend the same command writes, in world space: the exporters split
vertices at seams and convert axes and units, so vertices are matched by position.

Targets: the bundled demo head (an OBJ) and a shared game-style head that comes as a .glb split
at its UV seams (485 vertices at 462 positions) with a separate Eyes object.
"""
import json
import os
import subprocess
import sys

import bpy
import numpy as np
import pytest
from scipy.spatial import cKDTree

from blender_tests.helpers.paths import REPO_ROOT
from exclone_addon.core import data

SCRIPT = REPO_ROOT / "scripts" / "batch_clone.py"
SHAPES = ["jawOpen", "eyeBlink_L", "mouthSmile_L", "browInnerUp_L"]
TARGETS = {"demo_head": lambda shared: data.DEMO_HEAD_FILE,
           "lowpoly_glb": lambda shared: shared / "characters" / "mh_head_lowpoly.glb"}


def run_cli(target, out):
    env = dict(os.environ, PYTHONDONTWRITEBYTECODE="1")
    result = subprocess.run([sys.executable, str(SCRIPT), "--target", str(target), "--shapes",
                             ",".join(SHAPES), "--out", str(out), "--no-preview"],
                            cwd=out.parent, env=env, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr
    return json.loads(out.with_suffix(".json").read_text())


def world_keys(obj):
    """{key name: (n, 3) world-space positions} of a mesh object ("Basis" first)."""
    matrix = np.array(obj.matrix_world)
    keys = {}
    for block in obj.data.shape_keys.key_blocks:
        local = np.empty(len(block.data) * 3)
        block.data.foreach_get("co", local)
        keys[block.name] = local.reshape(-1, 3) @ matrix[:3, :3].T + matrix[:3, 3]
    return keys


def keyed_objects():
    return [obj for obj in bpy.context.scene.objects
            if obj.type == 'MESH' and obj.data.shape_keys is not None]


@pytest.fixture(scope="module", params=sorted(TARGETS))
def target(request, tmp_path_factory):
    """(target file, the face object's world-space keys in the .blend the CLI writes)."""
    if request.param == "demo_head":
        path = TARGETS["demo_head"](None)
    else:
        path = TARGETS[request.param](request.getfixturevalue("shared_data"))
    folder = tmp_path_factory.mktemp(request.param)
    report = run_cli(path, folder / "r.blend")
    bpy.ops.wm.read_factory_settings(use_empty=True)
    with bpy.data.libraries.load(str(folder / "r.blend")) as (source, loaded):
        loaded.objects = source.objects
    for obj in loaded.objects:
        bpy.context.scene.collection.objects.link(obj)
    bpy.context.view_layer.update()
    face = bpy.data.objects[report["outputs"]["target_object"]]
    return path, folder, world_keys(face)


@pytest.mark.parametrize("suffix", [".glb", ".fbx"])
def test_every_key_comes_back_with_its_name_and_vertex_motion(target, suffix):
    path, folder, expected = target
    written = folder / f"r_{suffix[1:]}{suffix}"        # its own report: r_glb.json
    run_cli(path, written)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    importer = bpy.ops.import_scene.gltf if suffix == ".glb" else bpy.ops.import_scene.fbx
    importer(filepath=str(written))
    keyed = keyed_objects()
    assert len(keyed) == 1, [obj.name for obj in keyed]
    keys = world_keys(keyed[0])
    basis, neutral = keys.pop(next(iter(keys))), expected[next(iter(expected))]
    assert list(keys) == SHAPES
    diagonal = np.linalg.norm(np.ptp(neutral, axis=0))
    # every imported vertex is a copy of one vertex of the result (exporters split at seams),
    # and every vertex of the result is written
    distance, match = cKDTree(neutral).query(basis)
    assert distance.max() <= 1e-5 * diagonal, distance.max() / diagonal
    assert len(np.unique(neutral[match], axis=0)) == len(np.unique(neutral, axis=0))
    for name in SHAPES:
        wanted = expected[name] - neutral
        error = np.linalg.norm((keys[name] - basis) - wanted[match], axis=1).max()
        assert error <= 1e-4 * diagonal, f"{name}: {error / diagonal:.2e} of the diagonal"
        assert np.linalg.norm(wanted, axis=1).max() > 1e-3 * diagonal, f"{name} does not move"
    print(f"{path.name} -> {suffix}: {len(basis)} vertices written for {len(neutral)}")
