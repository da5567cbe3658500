"""How the library's clones read on the shared MakeHuman characters (loaded by Blender, world
space, the face found by rendering and its head region solved): the expression measures of
core.expression_measures per head. The issue's bars: a blink leaves at most 10% of the open
height along the whole lid (met: the rims' station goals of core.rims), lips sealed at jawOpen +
mouthClose: the lips stand no more than 0.2% of the diagonal further apart than at rest (met;
they may press together past rest: the library's own lip landmarks do by 0.78% of its diagonal,
its lower lip folded under the upper), no edge stretched more than 2.5x beyond the source's
own stretch at jawOpen (met: core.transfer.STRETCH_BOUND), no triangle turned over at jawOpen
where the source's jawOpen turns over neither its image nor one beside it (expression_measures'
excess_flips; met: the library's own jawOpen turns 54 triangles of its inner lips over, rolling
them into the mouth, and a clone that follows it turns a few of their images over too). Where a
bar is met the test asserts the bar; elsewhere what is reached, with a margin, and says so.
Skipped without the shared data. Run with -s to see the figures."""
from functools import lru_cache

import pytest

import bpy

from blender_tests.helpers.character_files import load_into_scene
from blender_tests.helpers.paths import SHARED_DATA
from exclone_addon.blender import character as blender_character
from exclone_addon.core import character, expression_measures as em
from exclone_addon.core.cloning import clone_expressions
from exclone_addon.core.library import load_library

EXPRESSIONS = ["eyeBlink_L", "eyeBlink_R", "jawOpen", "mouthClose"]
BLINK_BAR = 0.10           # the issue's: a closing eye leaves at most this share of its opening
# file -> the face object.
# The male body's .glb (its vertices split at seams, numbered otherwise): blinks 0.7% / 0.4%,
# jawOpen's excess stretch 2.45x / 2.01x (.venv / .venv313), its lips sealed at -1.25% / -1.27%.
# The 67k-vertex dense head: blinks 1.4% / 1.3% (both venvs), jawOpen's excess stretch 2.50x /
# 2.44x (.venv / .venv313, at the bar), one triangle turned over at jawOpen (a sliver at the left
# mouth corner whose image the library's own jawOpen turns over), the lips sealed at -1.29% /
# -1.29% of the diagonal (pressed past rest).
# Blinks (.venv): male body 1.0% / 0.5%, child body 1.1% / 1.1%, stylised head 0.5% / 0.6%, old
# woman's body (the fbx's Body object alone) 0.8% / 0.3%, the 485-vertex low-poly head 4.2% / 4.5%
# (rows of three or four vertices; its corners the openings' ends as seen), since a closing eye's
# rows are brought together as the measures read them (core.rims._GapMatch.closed). With the
# station goals alone (numpy 1.26 and 2 alike): 8.0% / 7.8% (ICT's own blink leaves 8-10% at the
# inner station), 7.7% / 4.9%, 7.7% / 5.4%, 6.7% / 4.6%, 9.3% / 7.5%. With the rims' pull at a
# hundredth (rims.STATION_WEIGHT), short of their goals: 9.3% / 9.1%, 7.7-7.8% / 5.2-5.4%, 8.0% /
# 6.1%, 7.4% / 4.1%, the low-poly head 13.3% / 11.6%; before the rims' goals were matched to the
# rows' gap: 9.4% / 9.4%, 6.8% / 4.9-5.1%, 7.8% / 5.9%, 8.0% / 4.9% (the low-poly head's left
# lids not found, its right eye 91% open); with the vertex map's
# images: 24% / 18%, 35% / 35%, 67% / 49%; the old woman's left eye took them while the rows'
# smoothness was judged against a parabola: 27%). Excess stretch
# at jawOpen in .venv / .venv313 (Blender 5.0.1 and 5.2 load the heads 1e-15 apart; the worst
# edge, beside the mouth corners): male body 2.39 / 2.14, child body 1.83 / 1.83, stylised head
# 1.70 / 1.72, low-poly head 2.00 / 2.00, old woman's body 1.93 / 1.93 (excess_flips 0 on every
# file, its triangulated and decimated variants and both venvs; flipped triangles 0 / 0, 1 / 1,
# 0 / 0, 0 / 0, 1 / 0 since the transfer's own tangles are undone,
# core.transfer.TANGLED_WEIGHT: the child's and old woman's left are the library's own turn of
# the lower lip's inside; 3 / 1, 2 / 2, 0 / 0, 0 / 0, 2 / 0 before, and earlier draws 4 / 1,
# 0 / 2, 2 / 1); before the goals around a passing edge were capped
# (core.transfer.STRETCH_BOUND): 2.39 / 2.94, 1.83 / 2.81, 1.70 / 1.72, 2.0 / 2.0, 3.43 / 3.36
# (flips up to 4, 1, 0, 0, 3), each figure one draw from a wide spread
# (over the head and 6 copies moved by 1e-12 of its diagonal, .venv: male up to 4.43, child 4.67,
# low-poly 2.97; now 2.42, 1.87, 2.00, docs/method.md §8 "Stretch bounded"); before the straddling
# images took their source triangles' mean gradient (core.transfer.STRADDLE): 2.39 / 2.94,
# 2.15 / 2.73, 3.13 / 3.13, 2.0 / 2.0, 3.42 / 3.36. The library's corner strip stretches 7-37x and
# the mouth corners meet only to 0.05-0.26 mouth widths (docs/method.md §7, "At the mouth
# corners", which also checks the measure).
FACES = {
    "mh_male_body.blend": "Body",
    "mh_male_body.glb": "Body",
    "mh_child_body_expr.blend": "Body",
    "mh_female_old_body.fbx": "Body",
    "mh_stylised_head.blend": "Head",
    "mh_head_lowpoly.glb": "Head",
    "mh_head_dense.blend": "Head",
}
STRETCH_BAR = 2.5          # the issue's: no edge stretched more than this beyond the source's
OVERRUN = 0.4              # a closing upper lid passes below the lower lid's edge by no more
                           # than this share of the open height (expression_measures'
                           # lid_overrun; the ICT neutral's lid, dragged through by the child's
                           # closure before the rims carried its thickness: 0.58): 0.05-0.33
OTHER_EYE = 0.05           # the other eye's gap stays within this of its rest (1)
LIPS_PART = 0.01           # jawOpen parts the lips by at least this share of the diagonal
                           # (the stylised head, large cranium: 0.035; the others 0.04-0.06)
LIPS_SEALED = 0.002        # the bar: at jawOpen + mouthClose the lips stand at most this
                           # much (x the diagonal) further apart than at rest (stylised head 0.0017)
LIPS_PRESSED = 0.02        # reached: and press together past rest by less than this (male body
                           # 1.55%, old woman's body 1.39%, low-poly head 0.74%, child body 0.30%;
                           # the library's own 0.78%)


@lru_cache(maxsize=None)
def measured(file_name, decimated=False, triangulated=False):
    """The expression measures of the library's clone onto the file's face, beside the source;
    decimated: the face object through Decimate (collapse, ratio 0.5) first, applied, as a
    game-ready lower-poly head is made from it; triangulated: through Triangulate, applied, as
    many game exports are."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    face_object = load_into_scene(SHARED_DATA / "characters" / file_name)[FACES[file_name]]
    for wanted, kind in ((decimated, 'DECIMATE'), (triangulated, 'TRIANGULATE')):
        if not wanted:
            continue
        modifier = face_object.modifiers.new("game-ready", kind)
        if kind == 'DECIMATE':
            modifier.ratio = 0.5
        with bpy.context.temp_override(object=face_object, active_object=face_object):
            bpy.ops.object.modifier_apply(modifier=modifier.name)
    part = character.Part(face_object.name, blender_character.world_polymesh(face_object))
    face = character.find([part])
    library = load_library().subset(EXPRESSIONS)
    result = clone_expressions(library.mesh, library.deltas, library.names, face.head.mesh,
                               source_landmarks=library.automatic_landmarks,
                               source_modes=library.shape_modes,
                               face_guide=face.guide, fixed_vertices=face.head.fixed)
    found = em.measure_clone(face.head.mesh, result, source=library.mesh,
                             source_deltas=library.deltas)
    print(f"\n{file_name}{' decimated' if decimated else ''}"
          f"{' triangulated' if triangulated else ''}: " + "; ".join(
        f"{name}: " + ", ".join(f"{key} {row[key]:.4g}" for key in (
            "eyelid_gap_left", "eyelid_gap_right", "lid_overrun_left", "lid_overrun_right",
            "lip_gap", "excess_stretch", "flipped_triangles", "excess_flips")
            if row.get(key) is not None)
        for name, row in found.items()))
    return found


@pytest.mark.parametrize("file_name", sorted(FACES))
def test_blinks_close_on_their_own_side(file_name, shared_data):
    found = measured(file_name)
    for name, closing, other in (("eyeBlink_L", "left", "right"), ("eyeBlink_R", "right", "left")):
        row = found[name]
        assert row[f"eyelid_gap_{closing}"] <= BLINK_BAR, (name, row)
        assert row[f"lid_overrun_{closing}"] <= OVERRUN, (name, row)
        assert abs(row[f"eyelid_gap_{other}"] - 1.0) <= OTHER_EYE, (name, row)


@pytest.mark.parametrize("file_name", sorted(FACES))
def test_jaw_opens_without_excess_stretch(file_name, shared_data):
    jaw = measured(file_name)["jawOpen"]
    assert jaw["lip_gap"] > LIPS_PART
    assert jaw["excess_stretch"] <= STRETCH_BAR
    assert jaw["excess_flips"] == 0, jaw


@pytest.mark.parametrize("file_name", sorted(FACES))
def test_lips_seal_at_jaw_open_with_mouth_close(file_name, shared_data):
    gap = measured(file_name)[em.MEASURED_TOGETHER]["lip_gap"]
    assert -LIPS_PRESSED < gap <= LIPS_SEALED


def test_blink_closes_on_a_decimated_head(shared_data):
    """The stylised head through Decimate (collapse 0.5, applied: 2,096 vertices, a game-ready
    head): its rim vertices stand 0.1-0.2 stations apart, and on the right upper lid an edge
    triangle's nearest corner is the skin above the lid (0.113 eye widths beyond its neighbours'
    line), which made the row rough: the rims took the vertex map's goals and eyeBlink_R left
    68% of the open height; the row without it: 4.2% (both venvs). Its left eye, whose automatic
    corners land elsewhere than with the Eyes object beside it (inner corner vertex 1125 instead
    of 1621, the outer one on the upper lid: eye width 2.85 instead of 2.70), has vertex 1621 on
    both rows (where the lids meet) and took the vertex map's goals (its five-vertex rows read
    rough against a parabola): 83% / 63% left open in .venv / .venv313. Judged by their deepest
    notch its rows take the station goals, the vertex on both rows both goals (rims._Correction
    sums them): 9.99% / 10.05% at the inner station; with the goals met (rims.STATION_WEIGHT)
    the lids meet, -1.4% / -1.5% (just past each other), the right eye 4.0% / 3.9%."""
    found = measured("mh_stylised_head.blend", decimated=True)
    for closing, other in (("right", "left"), ("left", "right")):
        row = found[f"eyeBlink_{closing[0].upper()}"]
        assert row[f"eyelid_gap_{closing}"] <= BLINK_BAR, row
        assert abs(row[f"eyelid_gap_{other}"] - 1.0) <= OTHER_EYE, row


def test_blinks_close_on_a_decimated_triangulated_body(shared_data):
    """The man's Body through Decimate (collapse 0.5) and Triangulate (applied: a game-ready
    body): its rim vertices stand up to 0.4 stations apart, the edge between two of them one
    straight mesh edge, and beside a lower rim vertex an edge triangle's nearest corner is the
    skin below the lid (0.067 eye widths below the lid's edge as seen from the front, within 0.09
    of its neighbours' line). The left rows read rough against a cubic or parabola, the rims took
    the vertex map's goals and the closed lid crumpled: 11.4% / 11.8% open at the inner station
    (.venv / .venv313), the upper row 51-56% below the lower at the outer one. Now the measured
    rows leave that skin out (expression_measures.OFF_EDGE), the rows are judged by their deepest
    notch (rims.ROUGH) and the station goals pull rim and skin: 1.1% (both venvs), the lids
    crossing by 28% at most; with the goals met (rims.STATION_WEIGHT) 3.1%. The right eye,
    whose upper edge as seen rises into a fold at the outer corner (a notch of 0.29 of the open
    height: judged rough, the vertex map's goals), left 9.95% / 10.08%; now 6.0% (both venvs;
    the same body exported as .fbx keeps station goals there, docs/method.md §8)."""
    found = measured("mh_male_body.blend", decimated=True, triangulated=True)
    left, right = found["eyeBlink_L"], found["eyeBlink_R"]
    assert left["eyelid_gap_left"] <= BLINK_BAR, left
    assert right["eyelid_gap_right"] <= BLINK_BAR, right
    assert abs(left["eyelid_gap_right"] - 1.0) <= OTHER_EYE, left
    assert abs(right["eyelid_gap_left"] - 1.0) <= OTHER_EYE, right


def test_jaw_opens_on_a_triangulated_body(shared_data):
    """The old woman's Body through Triangulate (applied, as many game exports are): a few of
    its target triangles beside the mouth corners had their corners' images on both lips, which
    part at jawOpen (an image stretched 5x beyond the source triangles under its corners; in a
    batch job, where the automatic landmarks fell a hair differently, 105-110x: a torn corner,
    94.9x excess stretch and 27 flips). Such a straddling image now takes the mean gradient of
    the source triangles under its corners (core.transfer.STRADDLE): 5.0x -> 3.08x / 2.99x
    excess stretch at jawOpen (.venv / .venv313; the batch's 94.9x -> 3.21x); with the goals
    around a passing edge capped (core.transfer.STRETCH_BOUND) 1.79x (both venvs, no flips)."""
    jaw = measured("mh_female_old_body.fbx", triangulated=True)["jawOpen"]
    assert jaw["excess_stretch"] <= STRETCH_BAR, jaw
    assert jaw["excess_flips"] == 0, jaw
