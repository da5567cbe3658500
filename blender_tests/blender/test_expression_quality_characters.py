"""How the library's clones read on the shared MakeHuman characters (loaded by Blender, world
space, the face found by rendering and its head region solved): the expression measures of
core.expression_measures per head. The issue's bars (a blink leaves at most 10% of the open
height along the whole lid; no edge stretched more than 2.5x beyond the source's own stretch;
lips sealed at jawOpen + mouthClose within 0.2% of the diagonal) are not reached on these heads
yet: each test asserts what is reached, with a margin, and says so. Skipped without the shared
data. Run with -s to see the figures."""
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
# file -> (face object, reached figures: the closing eye's gap at eyeBlink_L and _R, the worst
# excess stretch at jawOpen, the flipped triangles at jawOpen); None: no lids are found (the
# low-poly head's lids are three vertices each)
REACHED = {
    "mh_male_body.blend": ("Body", (0.245, 0.176), 3.33, 5),
    "mh_child_body_expr.blend": ("Body", (0.354, 0.349), 2.76, 0),
    "mh_stylised_head.blend": ("Head", (0.666, 0.493), 2.05, 2),
    "mh_head_lowpoly.glb": ("Head", None, 1.84, 0),
}
GAP_MARGIN = 0.05          # of the open height
STRETCH_MARGIN = 1.25      # x the reached excess stretch: the worst edge is a tail figure, and the
                           # same code reached 2.05x / 2.41x (stylised head) and 3.33x / 2.98x (male
                           # body) with numpy 1.26 / numpy 2 (rounding amplified by the fit's rules)
FLIP_MARGIN = 3
OTHER_EYE = 0.05           # the other eye's gap stays within this of its rest (1)
LIPS_PART = 0.01           # jawOpen parts the lips by at least this share of the diagonal
                           # (the stylised head, large cranium: 0.013; the others 0.04-0.06)
LIPS_SEALED = 0.02         # reached: |gap| at jawOpen + mouthClose below 1.5% (bar: 0.2%)


@lru_cache(maxsize=None)
def measured(file_name):
    """The expression measures of the library's clone onto the file's face, beside the source."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    face_object = load_into_scene(SHARED_DATA / "characters" / file_name)[REACHED[file_name][0]]
    part = character.Part(face_object.name, blender_character.world_polymesh(face_object))
    face = character.find([part])
    library = load_library().subset(EXPRESSIONS)
    result = clone_expressions(library.mesh, library.deltas, library.names, face.head.mesh,
                               source_landmarks=library.automatic_landmarks,
                               face_guide=face.guide, fixed_vertices=face.head.fixed)
    found = em.measure_clone(face.head.mesh, result, source=library.mesh,
                             source_deltas=library.deltas)
    print(f"\n{file_name}: " + "; ".join(
        f"{name}: " + ", ".join(f"{key} {row[key]:.4g}" for key in (
            "eyelid_gap_left", "eyelid_gap_right", "lip_gap", "excess_stretch",
            "flipped_triangles") if row.get(key) is not None)
        for name, row in found.items()))
    return found


@pytest.mark.parametrize("file_name", sorted(REACHED))
def test_blinks_close_on_their_own_side(file_name, shared_data):
    found, reached = measured(file_name), REACHED[file_name][1]
    if reached is None:
        assert found["eyeBlink_L"]["eyelid_gap_left"] is None
        assert found["eyeBlink_L"]["eyelid_gap_left_reason"]
        return
    for (name, closing, other), gap in zip((("eyeBlink_L", "left", "right"),
                                            ("eyeBlink_R", "right", "left")), reached):
        row = found[name]
        assert row[f"eyelid_gap_{closing}"] <= gap + GAP_MARGIN, (name, row)
        assert abs(row[f"eyelid_gap_{other}"] - 1.0) <= OTHER_EYE, (name, row)


@pytest.mark.parametrize("file_name", sorted(REACHED))
def test_jaw_opens_without_more_stretch_than_reached(file_name, shared_data):
    found = measured(file_name)
    _, _, stretch, flips = REACHED[file_name]
    jaw = found["jawOpen"]
    assert jaw["lip_gap"] > LIPS_PART
    assert jaw["excess_stretch"] <= STRETCH_MARGIN * stretch
    assert jaw["flipped_triangles"] <= flips + FLIP_MARGIN
    assert abs(found[em.MEASURED_TOGETHER]["lip_gap"]) < LIPS_SEALED
