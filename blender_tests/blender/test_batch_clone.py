"""scripts/batch_clone.py: bad input fails with one clear line and touches nothing; a full run
writes the .blend, the report, the OBJs and the contact sheet; an output that cannot be written
is refused before the work or, if it fails later (a full disk), leaves nothing half-written.

The CLI runs as a subprocess of this Python (the bpy module), exactly as a user runs it.
"""
import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import bpy
import cv2
import numpy as np
import pytest

from blender_tests.helpers.paths import REPO_ROOT
from exclone_addon.core import character as core_character, data
from exclone_addon.blender import files, mesh_io
from exclone_addon.core.errors import ExCloneError
from exclone_addon.core.library import load_library
from exclone_addon.core.mesh import PolyMesh, read_obj, write_obj
from scripts import batch_clone, clone_worker
from scripts.exclone_cli import Outputs

SCRIPT = REPO_ROOT / "scripts" / "batch_clone.py"
DATA = REPO_ROOT / "exclone_addon" / "data"
FLAMENCO_TARGETS = ["/farm/heads/anna.obj", "/farm/more/anna.obj", "/farm/chars/Bob v2.blend:Head",
                    "/farm/chars/élodie.glb", "/farm/scan.final.fbx"]
FLAMENCO_STEMS = ["anna", "anna-2", "Bob_v2_Head", "_lodie", "scan.final"]
DEMO_HEAD = data.DEMO_HEAD_FILE


def run_cli(*args, cwd):
    env = dict(os.environ, PYTHONDONTWRITEBYTECODE="1")  # nothing may be written into the repo
    return subprocess.run([sys.executable, str(SCRIPT), *map(str, args)], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=900)


def hashes(*roots):
    """sha256 of every file under the given files/folders."""
    files = [p for root in roots for p in ([root] if root.is_file() else sorted(root.rglob("*")))
             if p.is_file()]
    return {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in files}


def save_blend(path, objects):
    """Save a .blend holding the given (name, PolyMesh or None, shape keys dict) objects."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    for name, mesh, keys in objects:
        if mesh is None:
            bpy.context.scene.collection.objects.link(bpy.data.objects.new(name, None))
            continue
        obj = mesh_io.object_from_mesh(name, mesh)
        if keys:
            mesh_io.write_shape_keys(obj, list(keys), np.stack(list(keys.values())))
    bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True)
    bpy.ops.wm.read_factory_settings(use_empty=True)


@pytest.fixture
def head():
    return read_obj(DEMO_HEAD)


@pytest.fixture
def inputs(tmp_path, head):
    """Input files of every kind in tmp_path/in (the CLI gets copies, never the repo's data)."""
    folder = tmp_path / "in"
    folder.mkdir()
    (folder / "head.obj").write_bytes(DEMO_HEAD.read_bytes())
    lift = np.zeros_like(head.vertices)
    lift[:, 1] = 0.01
    save_blend(folder / "keyed.blend", [("plain", head, {}), ("keyed", head, {"lift": lift})])
    save_blend(folder / "no_keys.blend", [("head", head, {})])
    save_blend(folder / "no_mesh.blend", [("Empty", None, {})])
    (folder / "text.blend").write_text("not a blend file\n")
    (folder / "empty.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")  # vertices, no faces
    (folder / "dot.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n")  # a 2-corner face
    line = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], dtype=float)
    write_obj(folder / "flat.obj", PolyMesh.from_faces(line, [[0, 1, 2], [1, 2, 3]]))
    mismatched = folder / "mismatched"
    mismatched.mkdir()
    write_obj(mismatched / "neutral.obj", head)
    write_obj(mismatched / "jawOpen.obj", PolyMesh.from_faces(head.vertices[:100], []))
    good = folder / "folder"
    good.mkdir()
    write_obj(good / "neutral.obj", head)
    write_obj(good / "jawOpen.obj", PolyMesh(head.vertices + 0.1, head.loop_totals, head.loop_vertices))
    (folder / "head.stl").write_text("solid head\nendsolid head\n")
    (folder / "no_meshes").mkdir()
    (folder / "earlier_exclone.blend").write_text("the result of an earlier run\n")
    return folder


def landmarks_file(folder, source, target):
    path = folder / "landmarks.json"
    path.write_text(json.dumps({"source": source, "target": target}))
    return path


BAD_INPUTS = {
    # case: (arguments relative to the inputs folder, words the one-line message must contain)
    "missing target": (["--target", "{in}/missing.obj"], "target not found"),
    "missing source": (["--source", "{in}/missing.blend"], "source not found"),
    "target not a blend file": (["--target", "{in}/text.blend"], "not a readable .blend"),
    "target has no mesh": (["--target", "{in}/no_mesh.blend"], "contains no mesh object"),
    "target object is not a mesh": (["--target", "{in}/no_mesh.blend:Empty"],
                                    "is not a mesh object"),
    "target object missing": (["--target", "{in}/keyed.blend:Nope"], "no object named 'Nope'"),
    "source without shape keys": (["--source", "{in}/no_keys.blend"],
                                  "no mesh object with shape keys"),
    "named source without shape keys": (["--source", "{in}/keyed.blend:plain"],
                                        "has no shape keys"),
    "source is an OBJ": (["--source", "{in}/head.obj"], "cannot hold shape keys"),
    "empty target": (["--target", "{in}/empty.obj"], "is empty"),
    "degenerate target": (["--target", "{in}/flat.obj"], "degenerate"),
    "target with a 2-corner face": (["--target", "{in}/dot.obj"],
                                    "dot.obj: mesh has a polygon with fewer than 3 corners"),
    "mismatched OBJ folder": (["--source", "{in}/mismatched"], "every expression OBJ must have"),
    "unsupported target type": (["--target", "{in}/head.stl"], "unsupported file type '.stl'"),
    "unknown shape": (["--shapes", "jawOpen,notAShape"], "unknown expression(s) notAShape"),
    "out overwrites the target": (["--target", "{in}/keyed.blend", "--out", "{in}/keyed.blend"],
                                  "refusing to overwrite the input file"),
    "export would overwrite the source": (["--source", "{in}/folder", "--export-dir", "{in}/folder"],
                                          "refusing to overwrite the input file"),
    "out not a blend": (["--out", "{in}/result.txt"], "--out must name a .blend, .glb or .fbx file"),
    "out exists": (["--target", "{in}/head.obj", "--out", "{in}/earlier_exclone.blend"],
                   "{in}/earlier_exclone.blend exists; give --overwrite to replace it"),
    "--overwrite with --resume": (["--overwrite", "--resume"],
                                  "--overwrite replaces what --resume keeps; give one of them"),
    "--format with one target": (["--format", "glb"], "--format is for several targets"),
    "--summary-only without targets": (["--summary-only"], "--summary-only is for several targets"),
    "unknown --format": (["--target", "{in}/head.obj", "--target", "{in}/keyed.blend",
                          "--format", "stl"], "argument --format: invalid choice: 'stl'"),
    "--preview with --no-preview": (["--preview", "{in}/p.png", "--no-preview"],
                                    "--preview names the contact sheet that --no-preview skips"),
    "unknown option": (["--colour", "red"], "unrecognized arguments: --colour red"),
    "--out with several targets": (["--target", "{in}/head.obj", "--target", "{in}/keyed.blend",
                                    "--out", "{in}/r.blend"], "--out names one file"),
    "--jobs with one target": (["--jobs", "2"], "--jobs is for several targets"),
    "--jobs 0": (["--target", "{in}/head.obj", "--target", "{in}/keyed.blend", "--jobs", "0"],
                 "argument --jobs: must be at least 1"),
    "--jobs inf": (["--target", "{in}/head.obj", "--target", "{in}/keyed.blend", "--jobs", "inf"],
                   "argument --jobs: must be a whole number, got 'inf'"),
    "target folder without meshes": (["--target", "{in}/no_meshes"], "holds no .blend, .obj"),
    # output locations are checked before any work
    "--out under a file": (["--out", "{in}/head.obj/r.blend"],
                           "cannot write {in}/head.obj/r.blend: {in}/head.obj is a file, not a folder"),
    "--report under a file": (["--report", "{in}/head.obj/r.json"],
                              "cannot write {in}/head.obj/r.json: {in}/head.obj is a file"),
    "--preview under a file": (["--preview", "{in}/head.obj/deeper/r.png"],
                               "cannot write {in}/head.obj/deeper/r.png: {in}/head.obj is a file"),
    "--export-dir under a file": (["--export-dir", "{in}/head.obj/objs"],
                                  "cannot write {in}/head.obj/objs: {in}/head.obj is a file"),
    "--export-dir is a file": (["--export-dir", "{in}/head.obj"],
                               "cannot write {in}/head.obj: {in}/head.obj is a file"),
    "--out-dir under a file": (["--target", "{in}/head.obj", "--target", "{in}/keyed.blend",
                                "--out-dir", "{in}/text.blend/results"],
                               "cannot write {in}/text.blend/results: {in}/text.blend is a file"),
    "batch --export-dir under a file": (["--target", "{in}/head.obj", "--target", "{in}/keyed.blend",
                                         "--export-dir", "{in}/head.obj/objs"],
                                        "cannot write {in}/head.obj/objs: {in}/head.obj is a file"),
}
# what the engine prints while cloning, e.g. "   40% registration"
PROGRESS = re.compile(r"^\s*\d+% ", re.MULTILINE)


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_bad_input_fails_with_one_line_and_changes_nothing(case, inputs, tmp_path):
    arguments, expected = BAD_INPUTS[case]
    before = hashes(inputs, DATA)
    result = run_cli(*[a.replace("{in}", str(inputs)) for a in arguments], cwd=tmp_path)
    assert result.returncode != 0
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr
    expected = expected.replace("{in}", str(inputs))
    assert lines[0].startswith("batch_clone: error: ") and expected in lines[0], lines[0]
    assert not PROGRESS.search(result.stdout), "refused only after cloning"
    assert hashes(inputs, DATA) == before
    assert not (tmp_path / "out").exists()


# The checks are core.landmarks.checked_pairs' (the one check of landmark ids); the CLI names the file.
BAD_LANDMARKS = {
    "not JSON": ("{source: [1, 2", "is not valid JSON"),
    "missing key": ({"source": [1, 2, 3, 4]}, 'must be {"source": [vertex ids], "target": [vertex ids]}'),
    "not a dict": ([1, 2, 3, 4], 'must be {"source": [vertex ids], "target": [vertex ids]}'),
    "different lengths": ({"source": [1, 2, 3, 4], "target": [1, 2, 3]},
                          "4 source ids but 3 target ids"),
    "too few": ({"source": [1, 2, 3], "target": [1, 2, 3]}, "at least 4 are needed"),
    "out of range": ({"source": [1, 2, 3, 4], "target": [1, 2, 3, 4244]},
                     "a target vertex id is outside 0..4243"),
    "not ids": ({"source": [1, 2, 3, 4.5], "target": [1, 2, 3, 4]}, "with whole-number ids"),
    "repeated": ({"source": [1, 2, 3, 3], "target": [1, 2, 3, 4]},
                 "a source vertex id is used twice"),
}


@pytest.mark.parametrize("case", sorted(BAD_LANDMARKS))
def test_bad_landmarks_fail_with_one_line(case, tmp_path):
    content, expected = BAD_LANDMARKS[case]
    path = tmp_path / "landmarks.json"
    path.write_text(content if isinstance(content, str) else json.dumps(content))
    before = hashes(path)
    result = run_cli("--landmarks", path, cwd=tmp_path)
    assert result.returncode != 0
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("batch_clone: error: "), result.stderr
    assert expected in lines[0] and f"landmarks file {path}" in lines[0], lines[0]
    assert hashes(path) == before


# -- input readers and the OBJ export, without the engine ---------------------------------------

def export_shapes(directory, neutral, names, deltas):
    with Outputs() as outputs:
        paths = batch_clone.export_shapes(outputs, directory, neutral, names, deltas)
        outputs.commit()
    return paths


def test_export_of_an_unmodified_obj_target_reproduces_it(tmp_path, head):
    target = files.load_target(str(DEMO_HEAD))
    paths = export_shapes(tmp_path, target.mesh, [], np.zeros((0, len(head.vertices), 3)))
    exported = read_obj(paths["neutral"])
    assert np.abs(exported.vertices - head.vertices).max() <= 1e-5
    assert np.array_equal(exported.loop_totals, head.loop_totals)
    assert np.array_equal(exported.loop_vertices, head.loop_vertices)
    # The object stands upright in Blender (OBJ is Y-up) while its mesh keeps file coordinates.
    assert tuple(target.obj.rotation_euler) == pytest.approx((np.pi / 2, 0, 0))


def test_export_of_a_blend_target_reproduces_its_vertices_and_adds_deltas(tmp_path, head):
    lift = np.zeros_like(head.vertices)
    lift[:, 1] = 0.25
    save_blend(tmp_path / "target.blend", [("other", head, {}), ("head", head, {})])
    target = files.load_target(f"{tmp_path / 'target.blend'}:head")
    assert [obj.name for obj in bpy.context.scene.objects] == ["head"]
    paths = export_shapes(tmp_path / "export", target.mesh, ["jaw/Open"], lift[None])
    assert sorted(p.name for p in paths.values()) == ["jaw_Open.obj", "neutral.obj"]
    neutral, shape = read_obj(paths["neutral"]), read_obj(paths["jaw/Open"])
    assert np.abs(neutral.vertices - head.vertices).max() <= 1e-5
    assert np.abs(shape.vertices - (head.vertices + lift)).max() <= 1e-5
    assert np.array_equal(shape.loop_vertices, head.loop_vertices)


def test_blend_source_gives_its_shape_keys(tmp_path, head):
    lift = np.zeros_like(head.vertices)
    lift[:, 1] = 0.01
    save_blend(tmp_path / "source.blend", [("a_plain", head, {}), ("keyed", head, {"lift": lift})])
    source = files.load_source(str(tmp_path / "source.blend"))
    assert source.description.endswith(":keyed")
    assert batch_clone.source_inputs(str(tmp_path / "source.blend")) == [tmp_path / "source.blend"]
    assert source.names == ["lift"]
    assert np.abs(source.deltas[0] - lift).max() <= 1e-6


@pytest.mark.parametrize("suffix", [".fbx", ".glb"])
def test_fbx_and_glb_sources_give_their_shape_keys(suffix, tmp_path, head):
    lift = np.zeros_like(head.vertices)
    lift[:, 1] = 0.01
    obj = mesh_io.object_from_mesh("keyed", head)
    mesh_io.write_shape_keys(obj, ["lift", "sink"], np.stack([lift, -lift]))
    path = tmp_path / f"source{suffix}"
    if suffix == ".fbx":
        bpy.ops.export_scene.fbx(filepath=str(path))
    else:
        bpy.ops.export_scene.gltf(filepath=str(path), export_morph=True)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    source = files.load_source(str(path))
    assert source.description == f"{path}:keyed"
    assert source.names == ["lift", "sink"]
    # Both formats are Y-up: exporter and importer convert the axes both ways (glTF may also
    # split vertices, so compare every vertex with the one displacement).
    assert np.abs(source.deltas[0] - [0, 0.01, 0]).max() <= 1e-6


def test_shapes_and_landmarks_are_checked_before_cloning(tmp_path):
    path = landmarks_file(tmp_path, [0, 1, 2, 3], [10, 11, 12, 13])
    assert batch_clone.read_landmarks(path, 100, 20)["target"].tolist() == [10, 11, 12, 13]
    with pytest.raises(ExCloneError, match=r"landmarks file .* a target vertex id is outside 0\.\.11"):
        batch_clone.read_landmarks(path, 100, 12)


# -- full runs: need the cloning engine ----------------------------------------------------------

@pytest.fixture(scope="module")
def default_run(tmp_path_factory):
    """The CLI with no arguments at all, from an empty working directory."""
    cwd = tmp_path_factory.mktemp("default_run")
    before = hashes(DATA)
    result = run_cli(cwd=cwd)
    assert result.returncode == 0, result.stderr
    assert hashes(DATA) == before, "the run modified the bundled data"
    return cwd, result


def test_default_run_writes_blend_report_and_preview(default_run, head):
    cwd, result = default_run
    out = cwd / "out"
    assert sorted(p.name for p in out.iterdir()) == [
        "demo_head_exclone.blend", "demo_head_exclone.json", "demo_head_exclone.png"]
    for name in ("demo_head_exclone.blend", "demo_head_exclone.json", "demo_head_exclone.png"):
        assert name in result.stdout
    assert "shape keys added" in result.stdout.splitlines()[-1]
    assert re.search(r"^measures: blink gap L -?\d+% R -?\d+%, stretch [\d.]+x the source's, "
                     r"\d+ flipped, \d+ beyond the source's$",
                     result.stdout, re.MULTILINE), result.stdout


def test_default_run_blend_has_one_shape_key_per_library_expression(default_run, head):
    cwd, _ = default_run
    with bpy.data.libraries.load(str(cwd / "out" / "demo_head_exclone.blend")) as (src, dst):
        assert src.objects == ["demo_head"]
        dst.objects = src.objects
    obj = dst.objects[0]
    names, deltas = mesh_io.shape_keys_from_object(obj)
    assert names == load_library().names
    assert np.abs(mesh_io.mesh_from_object(obj).vertices - head.vertices).max() <= 1e-5
    assert tuple(obj.rotation_euler) == pytest.approx((np.pi / 2, 0, 0))
    movement = np.linalg.norm(deltas, axis=2).max(axis=1)
    assert movement[names.index("jawOpen")] > 0.01 * np.ptp(head.vertices, axis=0).max()


def test_default_run_report(default_run):
    cwd, _ = default_run
    report = json.loads((cwd / "out" / "demo_head_exclone.json").read_text())
    assert report["counts"]["target_vertices"] == 4244
    assert report["counts"]["expressions"] == report["counts"]["shape_keys_added"] == 57
    assert report["timings"]["total"] >= report["timings"]["clone_total"] > 0
    assert report["quality"]
    marks = report["landmarks"]
    assert len(marks["source"]) == len(marks["target"]) == len(marks["names"]) >= 4
    assert report["versions"]["blender"] == bpy.app.version_string
    # the expression measures (core.expression_measures): every expression, and the summary
    measures = report["measures"]
    assert set(measures["expressions"]) == set(load_library().names) | {"jawOpen+mouthClose"}
    assert 0 <= measures["summary"]["eyeBlink_L_gap"] < 1
    assert measures["summary"]["eyeBlink_L_other_eye_gap"] == pytest.approx(1.0, abs=0.1)
    assert measures["summary"]["jawOpen_lip_gap"] > 0
    # measured beside the source: the stretch beyond the source's own
    assert measures["summary"]["worst_excess_stretch"] >= 1.0


def test_default_run_preview_shows_rendered_tiles(default_run):
    """Two rows of whole heads, then the close-ups: eyes at rest and blinking, mouth at rest
    and open (the closing and opening expressions are chosen by the measures)."""
    cwd, _ = default_run
    sheet = cv2.imread(str(cwd / "out" / "demo_head_exclone.png"))
    assert sheet is not None and sheet.shape == (3 * 320, 4 * 320, 3)
    tiles = [[sheet[row * 320:(row + 1) * 320, col * 320:(col + 1) * 320].astype(float)
              for col in range(4)] for row in range(3)]
    for row in range(3):
        for col in range(4):
            assert tiles[row][col][40:].std() > 10, f"tile {row},{col} is blank"
    # the close-ups show the face filling the tile, and the expressions change it
    eyes_rest, eyes_closing, mouth_rest, mouth_open = tiles[2]
    assert all((tile[40:] != tile[0, -1]).mean() > 0.9 for tile in tiles[2])
    def changed(rest, moved):        # share of the pixels the expression changes clearly
        return (np.abs(moved - rest)[40:].max(axis=2) > 20).mean()
    assert changed(eyes_rest, eyes_closing) > 0.005       # a lid over one eye
    assert changed(mouth_rest, mouth_open) > 0.1


def test_the_preview_falls_back_to_cycles(default_run):
    """Where Workbench cannot render, the sheet is rendered by CPU Cycles (the settings it needs
    exist in Blender 4.2+: scene.render.tile_size does not)."""
    from exclone_addon.blender import preview
    cwd, _ = default_run
    bpy.ops.wm.open_mainfile(filepath=str(cwd / "out" / "demo_head_exclone.blend"))
    head = bpy.data.objects["demo_head"]
    vertices = np.empty(3 * len(head.data.vertices))
    head.data.vertices.foreach_get("co", vertices)
    scene = bpy.context.scene
    preview._setup_scene(scene, head, vertices.reshape(-1, 3))
    preview._use_cycles(scene)
    tile, = preview._rendered_tiles(scene, head.data.shape_keys.key_blocks, ["jawOpen"])
    assert scene.render.engine == 'CYCLES' and tile[40:].std() > 10


def test_run_with_the_reports_landmarks_shapes_and_export(default_run, tmp_path, head):
    """Feeding the landmarks of the automatic run back in (the report lists them in the
    --landmarks form) gives the same landmarks; exported OBJs match the target and the keys;
    --no-preview renders and writes no contact sheet."""
    cwd, _ = default_run
    automatic = json.loads((cwd / "out" / "demo_head_exclone.json").read_text())["landmarks"]
    landmarks = landmarks_file(tmp_path, automatic["source"], automatic["target"])
    result = run_cli("--shapes", "jawOpen,eyeBlink_L", "--landmarks", landmarks,
                     "--export-dir", tmp_path / "objs", "--out", tmp_path / "r.blend",
                     "--no-preview", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["landmarks.json", "objs", "r.blend",
                                                          "r.json"]
    assert "preview" not in result.stdout
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["outputs"]["preview"] is None and "preview" not in report["timings"]
    assert report["landmarks"]["source"] == automatic["source"]
    assert report["landmarks"]["target"] == automatic["target"]
    assert report["counts"]["expressions"] == 2
    assert sorted(p.name for p in (tmp_path / "objs").iterdir()) == [
        "eyeBlink_L.obj", "jawOpen.obj", "neutral.obj"]
    neutral = read_obj(tmp_path / "objs" / "neutral.obj")
    assert np.abs(neutral.vertices - head.vertices).max() <= 1e-5
    with bpy.data.libraries.load(str(tmp_path / "r.blend")) as (src, dst):
        dst.objects = src.objects
    names, deltas = mesh_io.shape_keys_from_object(dst.objects[0])
    assert names == ["jawOpen", "eyeBlink_L"]
    jaw = read_obj(tmp_path / "objs" / "jawOpen.obj")
    assert np.abs(jaw.vertices - (head.vertices + deltas[0])).max() <= 1e-5


# -- batches of several targets ------------------------------------------------------------------

def test_an_obj_of_the_librarys_own_mesh_takes_its_expressions_vertex_by_vertex(tmp_path):
    """An ICT-FaceKit head (here the library's own mesh as an OBJ) is made from the library's
    base mesh: no registration, the report says so, and each key is the library's own motion,
    the eyelashes and eye shells too (through the registration they kept 74% of the blink's
    peak motion as error)."""
    library = load_library()
    write_obj(tmp_path / "ict.obj", library.mesh)
    result = run_cli("--target", tmp_path / "ict.obj", "--out", tmp_path / "ict.blend",
                     "--no-preview", "--shapes", "eyeBlink_L,mouthSmile_R", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "the source's own base mesh (" in result.stdout.splitlines()[-1], result.stdout
    report = json.loads((tmp_path / "ict.json").read_text())
    assert report["quality"]["shared_vertices"] > 0.95 * len(library.mesh.vertices)
    with bpy.data.libraries.load(str(tmp_path / "ict.blend")) as (src, dst):
        dst.objects = src.objects
    names, deltas = mesh_io.shape_keys_from_object(dst.objects[0])
    for name in ("eyeBlink_L", "mouthSmile_R"):
        truth = library.deltas[library.names.index(name)]
        peak = np.linalg.norm(truth, axis=1).max()
        error = np.linalg.norm(deltas[names.index(name)] - truth, axis=1) / peak
        for part, (start, stop) in library.parts.items():
            # the smile moves ICT's neck below the head's cut, held still (5.1% there)
            assert error[start:stop].max() < (0.06 if part == "face" else 0.02), (name, part)


def _blenders_parts(spec):
    """The Parts Blender makes of a target spec (files.load_target), its face not found."""
    parts = []
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    files.load_target(spec, find_face=lambda found: parts.extend(found) or
                      core_character.whole(found[0], 0))
    return parts


def write_head_with_a_duplicate_face(path):
    """The demo head with its first face twice: Blender's object of it (mesh validate) has the
    duplicate removed."""
    text = DEMO_HEAD.read_text()
    face = next(line for line in text.splitlines() if line.startswith("f "))
    path.write_text(text + "\n" + face + "\n")


def test_the_forked_clone_makes_the_object_blender_makes_of_an_obj(tmp_path):
    """The forked copy of the CLI (clone_worker) finds the face on the object it makes of an
    OBJ target without Blender; batch_clone uses it only if it is Blender's to the bit, which
    it is for the demo head and the library's own mesh (several parts, 26k vertices), and not
    for a mesh that Blender repairs (a duplicate face)."""
    write_obj(tmp_path / "ict.obj", load_library().mesh)
    write_head_with_a_duplicate_face(tmp_path / "repaired.obj")
    for spec, same in ((None, True), (str(tmp_path / "ict.obj"), True),
                       (str(tmp_path / "repaired.obj"), False)):
        parts = _blenders_parts(spec)
        assert len(parts) == 1
        assert clone_worker.same_part(clone_worker.target_part(spec), parts[0]) == same, spec
    assert clone_worker.target_part(str(tmp_path / "missing.obj")) is None


def test_a_target_the_fork_reads_otherwise_than_blender_gets_blenders_face(tmp_path):
    """An OBJ that Blender repairs: the forked copy's face is not used, the face is found on
    Blender's object and cloned; the keys and report are those of a run in one process
    (batch_clone.main here)."""
    target = tmp_path / "repaired.obj"
    write_head_with_a_duplicate_face(target)
    options = ["--target", str(target), "--no-preview", "--shapes", "jawOpen,eyeBlink_L"]
    result = run_cli(*options, "--out", tmp_path / "forked.blend", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert batch_clone.main(options + ["--out", str(tmp_path / "one.blend")]) == 0
    reports = [json.loads((tmp_path / f"{name}.json").read_text()) for name in ("forked", "one")]
    for key in ("quality", "landmarks", "measures", "counts"):
        assert reports[0][key] == reports[1][key], key
    keys = []
    for name in ("forked", "one"):
        with bpy.data.libraries.load(str(tmp_path / f"{name}.blend")) as (src, dst):
            dst.objects = src.objects
        keys.append(mesh_io.shape_keys_from_object(dst.objects[0]))
    assert keys[0][0] == keys[1][0] == ["jawOpen", "eyeBlink_L"]
    assert np.array_equal(keys[0][1], keys[1][1])


def test_output_names_are_unique_per_target():
    assert batch_clone.output_stems(["a/head.obj", "b/head.obj", "c/head.blend:Face", "head.fbx"]) == [
        "head", "head-2", "head_Face", "head-3"]
    # the names blender_tests/core/test_flamenco_job.py expects of flamenco/exclone_batch.js
    assert batch_clone.output_stems(FLAMENCO_TARGETS) == FLAMENCO_STEMS


def test_batch_writes_one_output_per_target_and_skips_a_bad_one(tmp_path, head):
    """A folder (two OBJs, one of them broken) plus a .blend object, two processes at once: the
    good targets get their files (no contact sheets: --no-preview reaches every target), the bad
    one is reported, the summary lists all three."""
    folder = tmp_path / "heads"
    folder.mkdir()
    (folder / "head.obj").write_bytes(DEMO_HEAD.read_bytes())
    (folder / "broken.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")   # no faces
    save_blend(tmp_path / "scene.blend", [("face", head, {})])
    before = hashes(folder, tmp_path / "scene.blend")
    result = run_cli("--target", folder, "--target", f"{tmp_path / 'scene.blend'}:face",
                     "--jobs", "2", "--shapes", "jawOpen,eyeBlink_L", "--out-dir", "results",
                     "--no-preview", cwd=tmp_path)
    assert result.returncode == 1
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        "batch_clone: error: 1 of 3 targets failed (first: "), result.stderr
    assert "broken.obj: target" in lines[0] and "is empty" in lines[0]
    assert hashes(folder, tmp_path / "scene.blend") == before

    out = tmp_path / "results"
    assert "batch: 3 target(s) to run, 2 at a time (--jobs)" in result.stdout
    assert sorted(p.name for p in out.iterdir()) == [
        "batch_report.json", "head_exclone.blend", "head_exclone.json",
        "scene_face_exclone.blend", "scene_face_exclone.json"]
    summary = json.loads((out / "batch_report.json").read_text())
    assert (summary["done"], summary["failed"], summary["skipped"], summary["jobs"]) == (2, 1, 0, 2)
    assert [entry.get("preview") for entry in summary["targets"]] == [None, None, None]
    status = {Path(entry["target"]).name: entry["status"] for entry in summary["targets"]}
    assert status == {"broken.obj": "failed", "head.obj": "done", "scene.blend:face": "done"}
    for name in ("head_exclone.blend", "scene_face_exclone.blend"):
        with bpy.data.libraries.load(str(out / name)) as (src, dst):
            dst.objects = src.objects
        names, deltas = mesh_io.shape_keys_from_object(dst.objects[0])
        assert names == ["jawOpen", "eyeBlink_L"]
        assert np.linalg.norm(deltas[0], axis=1).max() > 0.01 * np.ptp(head.vertices, axis=0).max()
    print(f"batch of 3 targets, 2 jobs: {summary['seconds']} s; per target: "
          + ", ".join(f"{Path(e['target']).name} {e['seconds']} s" for e in summary["targets"]))


# -- outputs that cannot be written: refused at once, or (a full disk) nothing left half-written --

MOUNT_SCRIPT = """
mount -t tmpfs -o "$1" exclone-test "$2" || exit 97
disk=$2; shift 2
"$@"; status=$?
echo "MOUNT CONTENTS:"; ls -A "$disk"
exit $status
"""


def run_cli_on_disk(disk, options, *args, cwd):
    """The CLI with the empty folder `disk` made a tmpfs with these mount options ("ro": a
    read-only disk, "size=64k": a nearly full one) in a private user and mount namespace: real
    write failures, for root as for anyone, and nothing outside the test changes. Returns
    (result, the files on that disk when the CLI ended)."""
    if shutil.which("unshare") is None:
        pytest.skip("needs unshare (util-linux) for a private tmpfs")
    env = dict(os.environ, PYTHONDONTWRITEBYTECODE="1")
    result = subprocess.run(["unshare", "--user", "--map-root-user", "--mount", "sh", "-c",
                             MOUNT_SCRIPT, "sh", options, str(disk), sys.executable, str(SCRIPT),
                             *map(str, args)],
                            cwd=cwd, env=env, capture_output=True, text=True, timeout=900)
    if result.returncode == 97 or result.stderr.startswith("unshare:"):
        pytest.skip(f"cannot mount a private tmpfs here: {result.stderr.strip()}")
    stdout, _, contents = result.stdout.partition("MOUNT CONTENTS:\n")
    return subprocess.CompletedProcess(result.args, result.returncode, stdout, result.stderr), \
        contents.split()


def one_error_line(result):
    assert result.returncode == 1
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("batch_clone: error: "), result.stderr
    return lines[0].removeprefix("batch_clone: error: ")


READ_ONLY_OUTPUTS = {
    # case: (arguments, with {ro} the read-only folder; the path the message names)
    "--out": (["--out", "{ro}/r.blend"], "{ro}/r.blend"),
    "--report": (["--report", "{ro}/r.json"], "{ro}/r.json"),
    "--preview": (["--preview", "{ro}/sheets/r.png"], "{ro}/sheets/r.png"),
    "--export-dir": (["--export-dir", "{ro}/objs"], "{ro}/objs"),
    "--out-dir": (["--target", "{in}/head.obj", "--target", "{in}/keyed.blend", "--out-dir", "{ro}"],
                  "{ro}"),
}


@pytest.mark.parametrize("case", sorted(READ_ONLY_OUTPUTS))
def test_output_on_a_read_only_disk_is_refused_before_any_work(case, inputs, tmp_path):
    arguments, named = READ_ONLY_OUTPUTS[case]
    read_only = tmp_path / "ro"
    read_only.mkdir()
    fill = {"{ro}": str(read_only), "{in}": str(inputs)}
    result, contents = run_cli_on_disk(
        read_only, "ro", *[re.sub(r"\{ro\}|\{in\}", lambda m: fill[m[0]], a) for a in arguments],
        cwd=tmp_path)
    message = one_error_line(result)
    assert message == (f"cannot write {named.replace('{ro}', str(read_only))}: the folder "
                       f"{read_only} is not writable"), message
    assert not PROGRESS.search(result.stdout), "refused only after cloning"
    assert contents == [] and sorted(p.name for p in tmp_path.iterdir()) == ["in", "ro"]


def test_a_blend_the_disk_cannot_hold_is_reported_and_nothing_is_left(tmp_path):
    """The .blend's folder is writable when checked but too small for the file: the failed save
    is noticed (Blender 5.0 reports this one as saved, leaving a truncated file, so the CLI reads
    each saved file back), no report or preview is written, nothing is left on the disk."""
    disk = tmp_path / "disk"
    disk.mkdir()
    result, contents = run_cli_on_disk(disk, "size=64k", "--shapes", "jawOpen",
                                       "--out", disk / "r.blend", "--report", tmp_path / "r.json",
                                       "--preview", tmp_path / "r.png", cwd=tmp_path)
    message = one_error_line(result)
    # Blender either notices the full disk itself or reports the truncated file as saved (then
    # the read-back catches it): both end in a line that says the disk is full
    assert message.startswith(f"cannot write {disk}/r.blend: "), message
    assert "disk full" in message or "No space left on device" in message, message
    assert PROGRESS.search(result.stdout), "the clone should have run (the check passed)"
    assert contents == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["disk"]


def test_a_failed_export_leaves_no_finished_blend_without_it(tmp_path):
    """--export-dir on a disk too small for the OBJs: the .blend, report and preview that were
    already written (under temporary names) are removed too; one line says what failed."""
    disk = tmp_path / "disk"
    disk.mkdir()
    result, contents = run_cli_on_disk(disk, "size=64k", "--shapes", "jawOpen",
                                       "--out", tmp_path / "r.blend",
                                       "--export-dir", disk / "objs", cwd=tmp_path)
    message = one_error_line(result)
    assert message == f"cannot write {disk}/objs/neutral.obj: No space left on device", message
    assert contents == []       # not even the objs folder the run made
    assert sorted(p.name for p in tmp_path.iterdir()) == ["disk"]


# -- big batches: jobs sized by the machine, one summary, resuming an interrupted batch ----------

GIB = 1024 ** 3


def test_jobs_are_sized_by_the_cpus_and_the_memory_available():
    per_job = batch_clone.JOB_BASE_BYTES + batch_clone.JOB_BYTES_PER_VERTEX * 50_000
    # plenty of memory: every CPU busy, never more jobs than targets
    assert batch_clone.plan_jobs(None, 50, [4_000, 50_000], 64 * GIB, 8)[0] == 8
    assert batch_clone.plan_jobs(None, 3, [4_000], 64 * GIB, 8)[0] == 3
    # memory for three of the largest target's jobs (after the margin left to others)
    available = 3.5 * per_job / batch_clone.MEMORY_MARGIN
    jobs, why = batch_clone.plan_jobs(None, 50, [4_000, 50_000], available, 8)
    assert jobs == 3 and "8 CPUs" in why and "GiB per target" in why
    # not even one fits: one at a time; unknown memory: the CPUs; --jobs as given
    assert batch_clone.plan_jobs(None, 50, [50_000], 0.1 * GIB, 8)[0] == 1
    assert batch_clone.plan_jobs(None, 50, [50_000], None, 8)[0] == 8
    assert batch_clone.plan_jobs(5, 50, [50_000], 0.1 * GIB, 8) == (5, "--jobs")
    assert batch_clone.available_memory() > 0


def test_a_targets_vertices_are_estimated_without_loading_it(tmp_path, head):
    assert batch_clone.estimated_vertices(str(DEMO_HEAD)) == len(head.vertices)
    glb = tmp_path / "head.glb"
    glb.write_bytes(bytes(32 * 1000))
    assert batch_clone.estimated_vertices(f"{glb}:Face") == 1000
    assert batch_clone.estimated_vertices(str(tmp_path / "missing.obj")) == 0


def write_moved_heads(folder, head, scales_and_shifts):
    """Copies of the demo head, scaled and moved (other sizes and places, the same face)."""
    folder.mkdir(exist_ok=True)
    for name, (scale, shift) in scales_and_shifts.items():
        write_obj(folder / f"{name}.obj", PolyMesh(head.vertices * scale + shift, head.loop_totals,
                                                   head.loop_vertices))


def test_an_interrupted_batch_resumes_and_a_broken_target_is_in_the_summary(tmp_path, head):
    """Two heads done by a first run (as if it was interrupted there); the whole folder, two
    more heads among them one broken, is refused without --resume (nothing is replaced), then
    with --resume the done heads are skipped, the new one is done, the broken one failed with
    its message, and the one summary lists all four."""
    folder = tmp_path / "heads"
    write_moved_heads(folder, head, {"a_small": (0.5, [0.0, 0.2, 0.0]),
                                     "b_large": (3.0, [1.0, 0.0, -2.0])})
    options = ["--shapes", "jawOpen,eyeBlink_L", "--out-dir", "results", "--no-preview"]
    first = run_cli("--target", folder, *options, cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    out = tmp_path / "results"
    done_before = hashes(out / "a_small_exclone.blend", out / "b_large_exclone.blend")

    write_moved_heads(folder, head, {"c_far": (1.0, [50.0, 0.0, 0.0])})
    (folder / "broken.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")   # no faces
    refused = run_cli("--target", folder, *options, cwd=tmp_path)
    assert refused.returncode == 1 and not PROGRESS.search(refused.stdout)
    assert "give --resume to skip the targets that are done, or --overwrite" in refused.stderr

    resumed = run_cli("--target", folder, "--jobs", "2", *options, "--resume", cwd=tmp_path)
    assert resumed.returncode == 1
    assert "1 of 4 targets failed (first: " in resumed.stderr and "is empty" in resumed.stderr
    assert hashes(out / "a_small_exclone.blend", out / "b_large_exclone.blend") == done_before
    summary = json.loads((out / "batch_report.json").read_text())
    entries = {Path(entry["target"]).stem: entry for entry in summary["targets"]}
    assert {name: entry["status"] for name, entry in entries.items()} == {
        "a_small": "skipped", "b_large": "skipped", "broken": "failed", "c_far": "done"}
    assert (summary["done"], summary["failed"], summary["skipped"]) == (1, 1, 2)
    assert "is empty" in entries["broken"]["error"]
    assert entries["c_far"]["output"] == str(Path("results") / "c_far_exclone.blend")
    assert entries["c_far"]["shape_keys_added"] == entries["a_small"]["shape_keys_added"] == 2
    assert entries["c_far"]["seconds"] > 0
    for line in ("a_small.obj: skipped, done in an earlier run", "c_far.obj: done, 2 shape keys",
                 "broken.obj: FAILED: target"):
        assert line in resumed.stdout, resumed.stdout

    # the summary of what is on disk, as a render farm's last task writes it
    only = run_cli("--target", folder, "--out-dir", "results", "--summary-only", cwd=tmp_path)
    assert only.returncode == 1 and not PROGRESS.search(only.stdout)
    summary = json.loads((out / "batch_report.json").read_text())
    assert [entry["status"] for entry in summary["targets"]] == ["done", "done", "failed", "done"]
    assert "its task did not finish" in summary["targets"][2]["error"]


def _terminal_sigint():
    """Ctrl-C's default action in the batch, as a shell started from a terminal gives it: a
    child inherits an ignored SIGINT, and Blender code run earlier in this test process may
    have set it so."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_ctrl_c_stops_a_batch_with_its_summary_and_resume_continues_it(tmp_path, head):
    """Ctrl-C (SIGINT to the batch's process group, as a terminal sends it) once the first head
    is done: the batch stops with one line saying how to continue, the summary lists the first
    head done and the second interrupted, nothing half-written is left; --resume then skips the
    first and does the second."""
    folder = tmp_path / "heads"
    write_moved_heads(folder, head, {"a_first": (1.0, [0.0, 0.0, 0.0]),
                                     "b_second": (2.0, [0.0, 1.0, 0.0])})
    options = ["--target", folder, "--jobs", "1", "--shapes", "jawOpen", "--out-dir", "results",
               "--no-preview"]
    env = dict(os.environ, PYTHONDONTWRITEBYTECODE="1")
    batch = subprocess.Popen([sys.executable, str(SCRIPT), *map(str, options)], cwd=tmp_path,
                             env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             start_new_session=True, preexec_fn=_terminal_sigint)
    out = tmp_path / "results"
    deadline = time.monotonic() + 900
    while not (out / "a_first_exclone.json").exists() and batch.poll() is None:
        assert time.monotonic() < deadline, "the first target never finished"
        time.sleep(0.2)
    time.sleep(1.0)                       # the second target's process has started
    os.killpg(batch.pid, signal.SIGINT)
    _, stderr = batch.communicate(timeout=300)
    assert batch.returncode == 1
    lines = stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("batch_clone: error: interrupted: 1 of 2 targets "
                                                   "done; run the same command with --resume"), stderr
    summary = json.loads((out / "batch_report.json").read_text())
    assert [(e["status"], e.get("error")) for e in summary["targets"]] == [
        ("done", None), ("failed", "interrupted")]
    assert sorted(p.name for p in out.iterdir()) == [
        "a_first_exclone.blend", "a_first_exclone.json", "batch_report.json"]

    resumed = run_cli(*options, "--resume", cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr
    summary = json.loads((out / "batch_report.json").read_text())
    assert [e["status"] for e in summary["targets"]] == ["skipped", "done"]
    assert (out / "b_second_exclone.json").is_file()
