"""The bundled ICT-FaceKit library, the OBJ-folder loader and the ARKit renaming."""
import json
import shutil

import numpy as np
import pytest

from blender_tests.helpers.paths import REPO_ROOT
from exclone_addon.core import data
from exclone_addon.core.errors import ExCloneError
from exclone_addon.core.library import (ARKIT_BLENDSHAPES, arkit_blendshapes,
                                        load_library, load_obj_folder)
from exclone_addon.core.mesh import PolyMesh, read_obj, write_obj
from exclone_addon.core.followers import TONGUE_OUT_JAW_OPEN

SHARED_ICT = REPO_ROOT.parent / "shared" / "data" / "ict-facekit"
DATA = REPO_ROOT / "exclone_addon" / "data"
# scripts/make_library.py drops deltas of at most 1e-6 cm (measured round-trip error: 1e-6 cm).
DELTA_TOLERANCE = 1.01e-6
ICT_EXTRAS = {"cheekRaiser_L", "cheekRaiser_R", "PupilDilate_L", "PupilDilate_R"}


@pytest.fixture(scope="module")
def library():
    return load_library()


@pytest.fixture(scope="module")
def ict():
    if not (SHARED_ICT / "expressions.npz").is_file():
        pytest.skip(f"shared ICT-FaceKit data not found at {SHARED_ICT}")
    with np.load(SHARED_ICT / "expressions.npz") as data:
        return {"names": [str(n) for n in data["names"]], "deltas": data["deltas"],
                "neutral": read_obj(SHARED_ICT / "neutral.obj")}


def test_bundled_library_loads(library):
    assert len(library.mesh.vertices) == 26719
    assert len(library.mesh.loop_totals) == 26384
    assert library.mesh.loop_totals.sum() == len(library.mesh.loop_vertices)
    assert len(library.names) == 57 and len(set(library.names)) == 57
    assert library.deltas.shape == (57, 26719, 3) and library.deltas.dtype == np.float64
    assert np.isfinite(library.mesh.vertices).all() and np.isfinite(library.deltas).all()
    assert library.landmarks68.shape == (68,)
    assert library.description == "the built-in ARKit library"
    # every expression moves something; jawOpen moves the chin by centimetres
    assert (np.abs(library.deltas).max(axis=(1, 2)) > 0).all()
    assert np.abs(library.deltas[library.names.index("jawOpen")]).max() > 1.0


def test_bundled_parts_tile_the_mesh(library):
    assert list(library.parts) == ["face", "head_and_neck", "mouth_socket", "eye_sockets",
                                   "gums_and_tongue", "teeth", "eyeballs", "eye_blend_occlusion",
                                   "eyelashes"]
    ranges = list(library.parts.values())
    assert ranges[0] == (0, 9409) and ranges[-1] == (25351, 26719)
    assert all(a[1] == b[0] for a, b in zip(ranges, ranges[1:]))
    # the 68 landmarks are all on the face part
    assert library.landmarks68.max() < library.parts["face"][1]


def test_bundled_file_size():
    assert data.LIBRARY_FILE.stat().st_size < 8e6


def test_bundled_licences_and_copies_present():
    for name in ["LICENSE-ICT-FaceKit.txt", "LICENSE-MakeHuman-CC0.md",
                 "LICENSE-MediaPipe-Apache-2.0.txt", "README.md"]:
        assert (DATA / name).stat().st_size > 500, name
    assert len(read_obj(DATA / "demo_head.obj").vertices) == 4244
    canonical = read_obj(DATA / "canonical_face.obj")
    assert len(canonical.vertices) == 468 and len(canonical.loop_totals) == 898


def test_bundled_matches_original(library, ict):
    assert library.names == ict["names"]
    assert np.abs(library.deltas - ict["deltas"]).max() <= DELTA_TOLERANCE
    neutral = ict["neutral"]
    np.testing.assert_array_equal(library.mesh.vertices, neutral.vertices.astype(np.float32))
    np.testing.assert_array_equal(library.mesh.loop_totals, neutral.loop_totals)
    np.testing.assert_array_equal(library.mesh.loop_vertices, neutral.loop_vertices)
    ids = json.loads((SHARED_ICT / "landmarks68.json").read_text())["multipie68_vertex_ids"]
    np.testing.assert_array_equal(library.landmarks68, ids)


def test_obj_folder_reproduces_original_deltas(ict, tmp_path):
    shutil.copy(SHARED_ICT / "neutral.obj", tmp_path)
    for path in (SHARED_ICT / "expressions_obj").glob("*.obj"):
        shutil.copy(path, tmp_path)
    lib = load_obj_folder(tmp_path)
    assert lib.names == ["eyeBlink_L", "jawOpen", "mouthSmile_L"]
    assert lib.landmarks68 is None and lib.parts == {}
    np.testing.assert_array_equal(lib.mesh.loop_vertices, ict["neutral"].loop_vertices)
    for name, delta in zip(lib.names, lib.deltas):
        original = ict["deltas"][ict["names"].index(name)]
        assert np.abs(delta - original).max() <= DELTA_TOLERANCE, name


def test_obj_folder_from_written_objs(tmp_path):
    neutral = read_obj(DATA / "demo_head.obj")
    shift = np.zeros_like(neutral.vertices)
    shift[:100, 1] = 0.25
    shutil.copy(DATA / "demo_head.obj", tmp_path / "neutral.obj")
    write_obj(tmp_path / "raise.obj", PolyMesh(neutral.vertices + shift, neutral.loop_totals,
                                               neutral.loop_vertices))
    write_obj(tmp_path / "lower.obj", PolyMesh(neutral.vertices - shift, neutral.loop_totals,
                                               neutral.loop_vertices))
    (tmp_path / "notes.txt").write_text("not an expression")
    lib = load_obj_folder(tmp_path)
    assert lib.names == ["lower", "raise"]
    assert lib.description == str(tmp_path)
    np.testing.assert_allclose(lib.deltas, np.stack([-shift, shift]), atol=1e-5)


def test_obj_folder_errors(tmp_path):
    with pytest.raises(ExCloneError, match="not found"):
        load_obj_folder(tmp_path / "missing")
    with pytest.raises(ExCloneError, match="no neutral.obj"):
        load_obj_folder(tmp_path)
    shutil.copy(DATA / "demo_head.obj", tmp_path / "neutral.obj")
    with pytest.raises(ExCloneError, match="no expression OBJs"):
        load_obj_folder(tmp_path)
    shutil.copy(DATA / "canonical_face.obj", tmp_path / "smile.obj")
    with pytest.raises(ExCloneError) as err:
        load_obj_folder(tmp_path)
    message = str(err.value)
    assert "smile.obj" in message and "468" in message and "4244" in message
    assert "\n" not in message


def test_load_library_errors(tmp_path):
    with pytest.raises(ExCloneError, match="not found"):
        load_library(tmp_path / "missing.npz")
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"this is not a zip file")
    with pytest.raises(ExCloneError, match="corrupt"):
        load_library(garbage)
    incomplete = tmp_path / "incomplete.npz"
    np.savez(incomplete, format_version=np.array(1), vertices=np.zeros((3, 3)))
    with pytest.raises(ExCloneError, match="corrupt"):
        load_library(incomplete)


def test_subset(library):
    sub = library.subset(["jawOpen", "eyeBlink_L"])
    assert sub.names == ["jawOpen", "eyeBlink_L"]
    np.testing.assert_array_equal(sub.deltas[0], library.deltas[library.names.index("jawOpen")])
    assert sub.mesh is library.mesh and sub.parts == library.parts
    assert sub.description == library.description
    assert sub.automatic_landmarks is library.automatic_landmarks
    with pytest.raises(ExCloneError) as err:
        library.subset(["jawOpen", "smileWide"])
    assert "smileWide" in str(err.value) and "mouthSmile_L" in str(err.value)


def test_arkit_name_list():
    assert len(ARKIT_BLENDSHAPES) == 52 and len(set(ARKIT_BLENDSHAPES)) == 52
    for name in ["eyeBlink_L", "jawOpen", "mouthSmile_L", "browInnerUp", "cheekPuff", "tongueOut"]:
        assert name in ARKIT_BLENDSHAPES


def test_arkit_blendshapes(library):
    names, deltas, missing = arkit_blendshapes(library.names, library.deltas)
    assert len(names) == 52 and deltas.shape == (52, 26719, 3)
    assert not ICT_EXTRAS & set(names) and missing == []
    assert names == ARKIT_BLENDSHAPES
    source = {name: library.deltas[i] for i, name in enumerate(library.names)}
    for combined in ["browInnerUp", "cheekPuff"]:
        np.testing.assert_array_equal(deltas[names.index(combined)],
                                      source[combined + "_L"] + source[combined + "_R"])
    np.testing.assert_array_equal(deltas[names.index("jawOpen")], source["jawOpen"])
    # tongueOut, not in the library, opens the jaw part of the way for the tongue
    np.testing.assert_array_equal(deltas[names.index("tongueOut")],
                                  TONGUE_OUT_JAW_OPEN * source["jawOpen"])


def test_arkit_blendshapes_needs_both_halves(library):
    keep = ["browInnerUp_L", "jawOpen"]
    sub = library.subset(keep)
    names, deltas, missing = arkit_blendshapes(sub.names, sub.deltas)
    assert names == ["jawOpen", "tongueOut"] and "browInnerUp" in missing and len(missing) == 50


def test_obj_folder_reads_only_the_expressions_vertices(tmp_path):
    # an expression's polygons are the neutral's: an exporter's vertices-only OBJ will do
    neutral = read_obj(DATA / "demo_head.obj")
    shutil.copy(DATA / "demo_head.obj", tmp_path / "neutral.obj")
    moved = neutral.vertices + 0.01
    (tmp_path / "up.obj").write_text("".join(f"v {float(x)!r} {float(y)!r} {float(z)!r}\n" for x, y, z in moved)
                                     + "f 1 2 99999\n")
    lib = load_obj_folder(tmp_path)
    np.testing.assert_array_equal(lib.deltas[0], moved - neutral.vertices)
