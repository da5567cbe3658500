"""scripts/batch_clone.py --out x.glb / x.fbx: the target with its new shape keys written through
Blender's own exporters. Each file is imported back into an empty scene and every key must move
every vertex as the clone did (the .obj export of the same run), in world space: the exporters
split vertices at seams and convert axes and units, so vertices are matched by position.
"""
import os
import subprocess
import sys

import bpy
import numpy as np
import pytest
from mathutils import Matrix
from scipy.spatial import cKDTree

from blender_tests.helpers.paths import REPO_ROOT
from exclone_addon.core.mesh import read_obj

SCRIPT = REPO_ROOT / "scripts" / "batch_clone.py"
SHAPES = ["jawOpen", "eyeBlink_L", "mouthSmile_L", "browInnerUp_L"]
# the OBJ target stands in Blender turned +90 degrees about X (OBJ is Y-up: files.load_target)
OBJ_TO_WORLD = np.array(Matrix.Rotation(np.pi / 2, 3, "X"))


def run_cli(*args, cwd):
    env = dict(os.environ, PYTHONDONTWRITEBYTECODE="1")
    return subprocess.run([sys.executable, str(SCRIPT), *map(str, args)], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=900)


@pytest.fixture(scope="module", params=[".glb", ".fbx"])
def written(request, tmp_path_factory):
    """The demo head (an OBJ target) cloned with SHAPES into r<suffix>, and the same keys as
    OBJs (--export-dir) to compare with."""
    folder = tmp_path_factory.mktemp(f"export{request.param}")
    result = run_cli("--shapes", ",".join(SHAPES), "--out", folder / f"r{request.param}",
                     "--export-dir", folder / "objs", "--no-preview", cwd=folder)
    assert result.returncode == 0, result.stderr
    assert sorted(p.name for p in folder.iterdir()) == ["objs", f"r{request.param}", "r.json"]
    return folder / f"r{request.param}", folder / "objs"


def imported_keys(path):
    """{key name: (n, 3) world-space positions} of the one mesh object imported from path
    ("Basis" included)."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    if path.suffix == ".glb":
        bpy.ops.import_scene.gltf(filepath=str(path))
    else:
        bpy.ops.import_scene.fbx(filepath=str(path))
    meshes = [obj for obj in bpy.context.scene.objects if obj.type == 'MESH']
    assert len(meshes) == 1, [obj.name for obj in meshes]
    obj = meshes[0]
    matrix = np.array(obj.matrix_world)
    keys = {}
    for block in obj.data.shape_keys.key_blocks:
        local = np.empty(len(block.data) * 3)
        block.data.foreach_get("co", local)
        local = local.reshape(-1, 3)
        keys[block.name] = local @ matrix[:3, :3].T + matrix[:3, 3]
    return keys


def test_every_key_comes_back_with_its_name_and_vertex_motion(written):
    path, objs = written
    neutral = read_obj(objs / "neutral.obj").vertices @ OBJ_TO_WORLD.T
    diagonal = np.linalg.norm(np.ptp(neutral, axis=0))
    keys = imported_keys(path)
    basis = keys.pop(next(iter(keys)))              # the first key block is the basis
    assert list(keys) == SHAPES
    # each imported vertex is a copy of one target vertex (exporters split at seams)
    distance, match = cKDTree(neutral).query(basis)
    assert distance.max() <= 1e-5 * diagonal, distance.max() / diagonal
    assert len(np.unique(match)) == len(neutral), "some target vertices were not written"
    for name in SHAPES:
        expected = read_obj(objs / f"{name}.obj").vertices @ OBJ_TO_WORLD.T - neutral
        error = np.linalg.norm((keys[name] - basis) - expected[match], axis=1).max()
        assert error <= 1e-4 * diagonal, f"{name}: {error / diagonal:.2e} of the diagonal"
        assert np.linalg.norm(expected, axis=1).max() > 1e-3 * diagonal, f"{name} does not move"
    print(f"{path.suffix}: {len(basis)} vertices written for {len(neutral)}")
