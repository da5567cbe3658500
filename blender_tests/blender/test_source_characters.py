"""A character as the SOURCE (issue #10 item 3): the CC0 child body's own MakeHuman expression
units (mh_child_body_expr.blend, a 13,380-vertex hm08 body) cloned onto the bundled demo head
and onto the ICT neutral (the bundled library's own mesh). The face is found on the body as on a
target, only its head region is the source (its keys' motion taken there, in the face's frame,
its landmarks found with the face's guide), through the command line's reading
(blender/files.load_source) and through the Clone operator with the body as the source object.

Asserted per unit, on the core.expression_measures measures of the clone beside its source:
nothing outside the head moves, no edge stretched more than 2.5x beyond the source's own stretch
(where that is not reached, the reached figure with a margin, named in REACHED), no more of the
face turned over than the source's own unit turns over (MakeHuman's units turn some over
themselves: mouth-open the inside of its lower lip, 98 triangles, each eye closure 17 at its inner
corner) and, at mouth-open, none turned over where the source's unit turns over neither its image
nor one beside it (expression_measures' excess_flips, item 1's jawOpen bar), the closing eye
closes and the other stays open, the mouth opens; and the motion is the source's: at every named
landmark the unit moves, the clone moves the same way (up for a smile's corners and a raised
brow, down for a closing lid), and over the solved face the clone's motion points where the
source's does at the corresponding points, at the same size relative to the face. Skipped
without the shared data. Run with -s to see the figures."""
import json
import os
import re
import subprocess
import sys
from functools import lru_cache

import bpy
import numpy as np
import pytest

from blender_tests.helpers.character_files import load_into_scene
from blender_tests.helpers.paths import REPO_ROOT, SHARED_DATA
from exclone_addon.blender import character, files, mesh_io, workflow
from exclone_addon.blender import landmarks as stored_landmarks
from exclone_addon.core import data, expression_measures as em
from exclone_addon.core.cloning import clone_expressions
from exclone_addon.core.library import load_library
from exclone_addon.core.mesh import read_obj, triangle_areas, triangle_normals

SOURCE_FILE = SHARED_DATA / "characters" / "mh_child_body_expr.blend"
pytestmark = pytest.mark.skipif(not SOURCE_FILE.is_file(),
                                reason=f"shared character {SOURCE_FILE} not found; this test "
                                       "needs ../shared/data/characters")

UNITS = ["eye-left-closure", "eye-right-closure", "mouth-open", "mouth-corner-puller",
         "mouth-depression", "eyebrows-left-up", "eyebrows-right-up", "eyebrows-left-down",
         "eyebrows-right-down", "mouth-pursing"]
TARGETS = ("demo_head", "ict_neutral")
STILL = 1e-4            # x the diagonal: the most anything outside the solved region may move
STRETCH_BAR = 2.5       # the bar: the clone's stretch beyond the source's own
FLIP_MARGIN = 3         # the target's triangles (of its median area) turned over beyond the area
                        # the source's own unit turns over, each face's area x its outer eye
                        # corners' distance squared. Areas, not counts: the ICT neutral's triangles
                        # are half the child's (median 4.2e-4 against 8.2e-4 eye widths squared),
                        # so turning over the same part of the lip as the source (mouth-open: the
                        # inside of the lower lip, the same region on front renders, 0.214
                        # against the child's 0.219) counts 546 triangles against 98
CLOSED = 0.1            # the bar: a closing eye leaves at most this share of its opening
CROSSED = -0.3          # its lids cross by no more than this share (demo head: 6%; 22-24% before
                        # the rims' station goals)
OVERRUN = 0.4          # the upper lid passes below the lower lid's edge by no more than this share
                        # of the open height (expression_measures' lid_overrun): the ICT
                        # neutral's lid thickness dragged through it at the outer half read 0.58
                        # (a notch on front renders) before the rims carried it with the edge
                        # (core.rims._thickness), 0.15 then, 0.26-0.27 with the thickness on
                        # the source's own left as transferred; the demo head 0.05-0.06; the child's
                        # own closures 0.29, the library's blinks cloned onto the shared heads
                        # 0.05-0.33
OPEN_EYE = 0.06         # the other eye's gap stays within this of its rest (1)
LIPS_PART = 0.02        # mouth-open parts the lips by at least this share of the diagonal
SAME_WAY = 0.85         # mean cosine of the clone's and the source's motion where the source moves
MOVING = 0.25           # ... where the source's motion is above this share of its largest
SIZE = (0.6, 1.6)       # the clone's motion / the source's (each x its face's outer eye corners'
                        # distance)
# The motion is compared on the solved region only (expression_measures.solved_vertices): the
# ICT neutral's eyeballs, lashes, eye occlusion, teeth, gums and mouth socket have no counterpart
# on the child's skin, and the skin nearest them (the source's image there) is the lid or lip
# over them, moving as they must not. Counted with them, the closing eyes' still eyeballs read
# as motion 0.51 in cosine and 0.42 in size, the pursed mouth's and the smile's still teeth and
# gums 0.54 and 0.65 (on the skin alone 0.95-0.97 / 0.80, 0.995, 0.98); the demo head is all skin.
# (target, unit) -> the figures reached where a bar above is not (measured, not tuned away).
# On the demo head the closures meet the bar: the child's own lids leave 9.7% and 6.3% at the
# inner station, and the rims' station goals left the demo head's 10.7% and 8.5% there (12.5%
# and 11.2-11.8% held short of them; crossed by 22% with the goals at the vertex map's images)
# until a closing eye's rows were brought together as read (0.6% / 0.7%); its mouth-open meets
# the bar since the vertex map measures an image's edges along the source (1.6-2.1x; it was
# 2.8-3.0x, the upper lip's inside hanging down with the jaw in spikes where its corners' images
# lay across the closed lips). On the ICT neutral (seen on front renders; its lids close to 0.3%
# / 0.3%, 8.3% / 4.9% with the station goals alone, 44% / 50% before the rims): the mouth-open
# turns over the inside of the lower lip as the child's own unit does (the same region on front
# renders: 0.2106 / 0.2142 eye widths squared with numpy 1.26 / 2, against the unit's own
# 0.2193). Checked with margins: turned-over area + 10%, eyelid gap + 0.05 (where one is
# reached). Every excess stretch meets the bar since the goals
# around a passing edge are capped (core.transfer.STRETCH_BOUND; numpy 1.26 / 2): the demo head's
# eye closures 2.19 / 1.82x and 2.34 / 1.66x (2.89 / 1.87x and 3.06 / 1.71x before: the worst
# edge at the lids' outer corners, within 0.03 eye widths of the corner landmark), the ICT
# neutral's mouth-open 2.42 / 2.49x (6.43 / 4.48x: a short edge 0.07 eye widths from the right
# mouth corner) and its smile 2.42 / 2.43x (3.00 / 3.26x).
REACHED = {
    ("ict_neutral", "mouth-open"): {"turned_over": 0.2142},
}
# unit -> (landmark, axis of the face's frame (0 left, 1 up, 2 forward), sign) it must move along,
# as the source moves it there; None: the mean motion where the source's motion is MOVING
MOVES = {
    "eye-left-closure": [("eyelid_upper_left", 1, -1)],
    "eye-right-closure": [("eyelid_upper_right", 1, -1)],
    "mouth-open": [("lower_lip", 1, -1), ("chin", 1, -1)],
    "mouth-corner-puller": [("mouth_corner_left", 1, 1), ("mouth_corner_right", 1, 1)],
    "mouth-depression": [("mouth_corner_left", 1, -1), ("mouth_corner_right", 1, -1)],
    "eyebrows-left-up": [("brow_mid_left", 1, 1)],
    "eyebrows-right-up": [("brow_mid_right", 1, 1)],
    "eyebrows-left-down": [(None, 1, -1)],        # the inner brow: no landmark there
    "eyebrows-right-down": [(None, 1, -1)],
    "mouth-pursing": [("upper_lip", 2, 1), ("lower_lip", 2, 1)],
}
# unit -> the landmark on the other side that stays (nearly) still
STAYS = {"eye-left-closure": "eyelid_upper_right", "eye-right-closure": "eyelid_upper_left",
         "eyebrows-left-up": "brow_mid_right", "eyebrows-right-up": "brow_mid_left"}
ALONG = 0.5             # the landmark's motion along its axis: at least this share of its length
OTHER_SIDE = 0.15       # the still side's landmark moves at most this share of the moving one's


def reached(target_name, unit, measure, bar):
    """The bar a figure is held to: the issue's, else the reached figure with its margin."""
    figure = REACHED.get((target_name, unit), {}).get(measure)
    if figure is None:
        return bar
    return {"turned_over": lambda: 1.1 * figure,
            "eyelid_gap": lambda: figure + 0.05, "cosine": lambda: figure - 0.05,
            "size": lambda: 0.8 * figure}[measure]()


@lru_cache(maxsize=None)
def source():
    """The body's units as the command line reads them (the head region of its found face)."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return files.load_source(str(SOURCE_FILE))


@lru_cache(maxsize=None)
def source_turn():
    """(3, 3) the source face's frame (columns: its left, up, forward in the body's coordinates,
    which are the world's: the body's transform is identity), as found on the body."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    body = load_into_scene(SOURCE_FILE)["Body"]
    return workflow.character_face(character.parts([body])).turn


@lru_cache(maxsize=None)
def cloned(target_name):
    """(target face, CloneResult, measures, source images (rest, deltas) at the target's
    vertices, (n,) bool the target's vertices in the solved region) of the body's units onto the
    target, as the command line clones them."""
    library = source()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    if target_name == "demo_head":
        face = files.load_target(None).face
    else:
        obj = mesh_io.object_from_mesh("ict_neutral", load_library().mesh)
        bpy.context.view_layer.update()
        face = workflow.character_face(character.parts([obj]))
    assert face.guide is not None, f"no face found on the {target_name}"
    result = clone_expressions(library.mesh, library.deltas, library.names, face.head.mesh,
                               source_landmarks=library.automatic_landmarks,
                               face_guide=face.guide, fixed_vertices=face.head.fixed)
    measures = em.measure_clone(face.head.mesh, result, source=library.mesh,
                                source_deltas=library.deltas)
    images = em.source_images(face.head.mesh.vertices, library.mesh, library.deltas, result)
    solved = em.solved_vertices(face.head.mesh, result)
    print(f"\n{target_name}: " + "; ".join(
        f"{name}: " + ", ".join(f"{key} {row[key]:.3g}" for key in (
            "eyelid_gap_left", "eyelid_gap_right", "lid_overrun_left", "lid_overrun_right",
            "lip_gap", "excess_stretch", "flipped_triangles", "excess_flips", "motion_outside")
            if row.get(key) is not None)
        for name, row in measures.items()))
    return face, result, measures, images, solved


def _turned_over(vertices, triangles, delta, width):
    """(area of the triangles `delta` turns over / width squared, (T,) each triangle's area /
    width squared)."""
    areas = triangle_areas(vertices, triangles) / width ** 2
    rest = triangle_normals(vertices, triangles)
    turned = np.einsum("ij,ij->i", triangle_normals(vertices + delta, triangles), rest) < 0
    return float(areas[turned].sum()), areas


@lru_cache(maxsize=None)
def source_turned_over():
    """{unit: the area its own unit turns over on the source's head region, x the source face's
    outer eye corners' distance squared}."""
    library = source()
    vertices, triangles = library.mesh.vertices, library.mesh.triangles()
    width = _eye_width(vertices, *library.automatic_landmarks)
    return {name: _turned_over(vertices, triangles, delta, width)[0]
            for name, delta in zip(library.names, library.deltas)}


def test_the_body_is_cut_to_its_head_with_its_units():
    library = source()
    assert library.names == UNITS
    assert library.head is not None and library.head.total == 13380
    assert 3500 < len(library.head.vertex_ids) < 6000         # the head, not the body
    names = list(library.automatic_landmarks[0])
    assert {"nose_tip", "upper_lip", "lower_lip", "mouth_corner_left", "eyelid_upper_left",
            "brow_mid_right"} <= set(names)
    # every unit's motion lies in the head: the cut dropped none of it
    bpy.ops.wm.read_factory_settings(use_empty=True)
    body = load_into_scene(SOURCE_FILE)["Body"]
    _, whole = mesh_io.shape_keys_from_object(body)
    moved = np.linalg.norm(whole, axis=2).max(axis=0) > 1e-6
    assert np.isin(np.flatnonzero(moved), library.head.vertex_ids).all()
    assert np.allclose(np.linalg.norm(library.deltas, axis=2).max(axis=1),
                       np.linalg.norm(whole, axis=2).max(axis=1))


@pytest.mark.parametrize("target_name", TARGETS)
@pytest.mark.parametrize("unit", UNITS)
def test_measures(target_name, unit):
    face, result, measures, _, solved = cloned(target_name)
    row = measures[unit]
    assert row["excess_stretch"] <= reached(target_name, unit, "excess_stretch", STRETCH_BAR), row
    vertices, triangles = face.head.mesh.vertices, face.head.mesh.triangles()
    triangles = triangles[solved[triangles].all(axis=1)]
    turned, areas = _turned_over(
        vertices, triangles, result.deltas[result.names.index(unit)],
        _eye_width(vertices, result.landmark_names, result.target_landmarks))
    print(f"\n{target_name} {unit}: turned over {turned:.4g} (source {source_turned_over()[unit]:.4g})"
          f" x eye width squared, {row['flipped_triangles']} triangles")
    assert turned <= reached(target_name, unit, "turned_over", source_turned_over()[unit]
                             + FLIP_MARGIN * np.median(areas)), row
    side = {"eye-left-closure": ("left", "right"), "eye-right-closure": ("right", "left")}
    if unit in side:
        closing, other = side[unit]
        assert CROSSED <= row[f"eyelid_gap_{closing}"] <= reached(target_name, unit, "eyelid_gap",
                                                                  CLOSED), row
        assert row[f"lid_overrun_{closing}"] <= OVERRUN, row
        assert abs(row[f"eyelid_gap_{other}"] - 1.0) <= OPEN_EYE, row
    elif not unit.startswith("eyebrows"):        # a raised brow opens its eye a little
        assert all(abs(row[f"eyelid_gap_{eye}"] - 1.0) <= OPEN_EYE for eye in ("left", "right"))
    if unit == "mouth-open":
        assert row["lip_gap"] > LIPS_PART, row
        # item 1's jawOpen bar: no triangle turned over where the source's unit turns over
        # neither its image nor one beside it (expression_measures' excess_flips)
        assert row["excess_flips"] == 0, row
    elif unit != "mouth-pursing":               # the pursed lips part a little, as the source's
        assert abs(row["lip_gap"]) < LIPS_PART, row
    # the demo head is one piece: nothing but the solved skin may move. The ICT neutral's other
    # parts (lashes, eye occlusion, teeth, gums, tongue) follow by rules: never further than the
    # skin moves
    if target_name == "demo_head":
        assert row["motion_outside"] < STILL, row
    else:
        skin = np.linalg.norm(result.deltas[result.names.index(unit)], axis=1).max()
        diagonal = np.linalg.norm(np.ptp(face.head.mesh.vertices, axis=0))
        assert row["motion_outside"] * diagonal <= skin, row


def _landmark_motion(names, ids, deltas, name):
    return deltas[ids[list(names).index(name)]]


@pytest.mark.parametrize("target_name", TARGETS)
@pytest.mark.parametrize("unit", UNITS)
def test_the_clone_moves_as_the_source(target_name, unit):
    face, result, _, (_, image_deltas), solved = cloned(target_name)
    library = source()
    row = result.names.index(unit)
    # the clone is in the target face's frame (its head mesh's), the source in its own
    # coordinates: both in their face's frame
    clone = result.deltas[row]
    own = library.deltas[library.names.index(unit)] @ source_turn()
    image_deltas = image_deltas @ source_turn()
    src_names, src_ids = library.automatic_landmarks
    image = image_deltas[row]
    size = np.linalg.norm(image, axis=1)
    moving = solved & (size > MOVING * size[solved].max())
    for name, axis, sign in MOVES[unit]:
        if name is None:
            theirs, ours = image[moving].mean(axis=0), clone[moving].mean(axis=0)
            assert sign * theirs[axis] > ALONG * np.linalg.norm(theirs), theirs
            assert sign * ours[axis] > ALONG * np.linalg.norm(ours), (ours, theirs)
            continue
        theirs = _landmark_motion(src_names, src_ids, own, name)
        assert sign * theirs[axis] > ALONG * np.linalg.norm(theirs), (name, theirs)   # the source
        ours = _landmark_motion(result.landmark_names, result.target_landmarks, clone, name)
        assert sign * ours[axis] > ALONG * np.linalg.norm(ours), (name, ours, theirs)
        if unit in STAYS:
            still = _landmark_motion(result.landmark_names, result.target_landmarks, clone,
                                     STAYS[unit])
            assert np.linalg.norm(still) < OTHER_SIDE * np.linalg.norm(ours), (still, ours)
    # over the face: the same direction and size as the source's at the corresponding points
    ours, theirs = clone[moving], image[moving]
    cosine = np.einsum("ij,ij->i", ours, theirs) / np.maximum(
        np.linalg.norm(ours, axis=1) * size[moving], 1e-300)
    src_width = _eye_width(library.mesh.vertices, src_names, src_ids)
    tgt_width = _eye_width(face.head.mesh.vertices, result.landmark_names, result.target_landmarks)
    ratio = (np.linalg.norm(ours, axis=1).mean() / tgt_width) / (size[moving].mean() / src_width)
    print(f"\n{target_name} {unit}: {moving.sum()} vertices, mean cosine {cosine.mean():.3f}, "
          f"size ratio {ratio:.2f}")
    assert cosine.mean() > reached(target_name, unit, "cosine", SAME_WAY)
    assert reached(target_name, unit, "size", SIZE[0]) < ratio < SIZE[1]


def _eye_width(vertices, names, ids):
    """The distance between the outer eye corners (landmarks names, ids on vertices)."""
    corners = [ids[list(names).index(f"eye_outer_{side}")] for side in ("left", "right")]
    return float(np.linalg.norm(vertices[corners[0]] - vertices[corners[1]]))


def test_the_clone_operator_takes_the_body_as_its_source():
    """In Blender: the body selected as the source object, the demo head active: Clone writes
    the body's 10 units on the head, cut to the body's face (its mouth opens, its left lid comes
    down, the right one stays), and the body's own keys are left as they were."""
    body = load_into_scene(SOURCE_FILE)["Body"]
    mesh = read_obj(data.DEMO_HEAD_FILE)         # Y up, as the file's coordinates
    head = mesh_io.object_from_mesh("head", mesh)
    body_keys = mesh_io.shape_keys_from_object(body)[1].copy()
    bpy.context.view_layer.objects.active = head
    for obj in (head, body):
        obj.select_set(True)
    assert bpy.ops.exclone.clone_expressions(preset="fast") == {'FINISHED'}
    names, deltas = mesh_io.shape_keys_from_object(head)
    assert names == UNITS
    assert np.array_equal(mesh_io.shape_keys_from_object(body)[1], body_keys)
    marks = workflow.face_landmarks(workflow.character_face(character.parts([head])))
    diagonal = np.linalg.norm(np.ptp(mesh.vertices, axis=0))
    opened = deltas[UNITS.index("mouth-open")]
    assert opened[marks["upper_lip"], 1] - opened[marks["lower_lip"], 1] > LIPS_PART * diagonal
    closing = deltas[UNITS.index("eye-left-closure")]
    down = -closing[marks["eyelid_upper_left"], 1]
    assert down > 0.01 * diagonal
    assert np.linalg.norm(closing[marks["eyelid_upper_right"]]) < OTHER_SIDE * down


def test_the_command_line_takes_the_body_as_its_source(tmp_path):
    """batch_clone.py --source the body file: the report names the source's head region, its
    landmarks are given in the body's own numbering (on its head: a run can be repeated with
    them as --landmarks), and the mouth opens."""
    out = tmp_path / "head.blend"
    done = subprocess.run([sys.executable, str(REPO_ROOT / "scripts" / "batch_clone.py"),
                           "--source", str(SOURCE_FILE), "--shapes", "mouth-open,eye-left-closure",
                           "--out", str(out), "--no-preview"],
                          capture_output=True, text=True, timeout=900,
                          env=dict(os.environ, PYTHONDONTWRITEBYTECODE="1"))
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(out.with_suffix(".json").read_text())
    assert report["inputs"]["source"] == f"{SOURCE_FILE}:Body"
    assert re.fullmatch(r"head region: [3-5],\d{3} of 13,380 vertices",
                        report["inputs"]["source_region"])
    assert report["counts"]["source_vertices"] < 6000
    library = source()
    marks = dict(zip(report["landmarks"]["names"], report["landmarks"]["source"]))
    assert np.isin(list(marks.values()), library.head.vertex_ids).all()
    assert marks["nose_tip"] == library.head.own_ids(
        [library.automatic_landmarks[1][library.automatic_landmarks[0].index("nose_tip")]])[0]
    found = report["measures"]["expressions"]
    assert found["mouth-open"]["lip_gap"] > LIPS_PART
    assert found["eye-left-closure"]["eyelid_gap_left"] <= reached("demo_head", "eye-left-closure",
                                                                   "eyelid_gap", CLOSED)


def test_auto_landmarks_put_the_bodys_on_its_face():
    """Auto Landmarks with the body as the source object: its landmarks are the ones Clone uses
    (on the head region of its found face), stored in the body's own numbering."""
    library = source()                  # first: it reads the file into a fresh scene
    bpy.ops.wm.read_factory_settings(use_empty=True)
    body = load_into_scene(SOURCE_FILE)["Body"]
    head = mesh_io.object_from_mesh("head", read_obj(data.DEMO_HEAD_FILE))
    bpy.context.scene.exclone.source_mode = 'OBJECT'
    bpy.context.view_layer.objects.active = head
    for obj in (head, body):
        obj.select_set(True)
    assert bpy.ops.exclone.auto_landmarks() == {'FINISHED'}
    names, ids = library.automatic_landmarks
    assert stored_landmarks.stored(body) == dict(zip(names, library.head.own_ids(ids).tolist()))
