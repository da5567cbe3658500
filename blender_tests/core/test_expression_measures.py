"""Expression measures (core.expression_measures): known answers on a flat face with eye holes,
on the demo head (eyes modelled as sockets), on the bundled library's own mesh and on a real
clone, and MakeHuman's own blink on its own topology."""
from functools import lru_cache
from types import SimpleNamespace

import numpy as np
import pytest

from exclone_addon.core import data, library, mesh
from exclone_addon.core import expression_measures as em
from exclone_addon.core.cloning import CloneResult, clone_expressions
from exclone_addon.core.landmarks import automatic_landmarks
from exclone_addon.core.mesh import PolyMesh
from exclone_addon.core.orientation import face_frame
from exclone_addon.core.reports import flips_phrase, measures_clause
from exclone_addon.core.surface import Surface

STEP = 0.05


# ------------------------------------------------------------------------------ a flat face

def _grid_index(x, y):
    """Vertex id of the grid point (x, y) on [-1, 1]^2 in steps of STEP."""
    n = round(2 / STEP) + 1
    return round((y + 1) / STEP) * n + round((x + 1) / STEP)


def _in_eye(x, y):
    """Inside one of the two rectangular eye holes: x in [0.2, 0.6] (mirrored), y in [0.3, 0.4]."""
    return 0.2 < abs(x) < 0.6 and 0.3 < y < 0.4


def flat_face(eye_holes=True):
    """A flat face in the x-y plane looking along +z: a grid with two eye holes (open height
    0.1, corners at (+-0.2, 0.35) and (+-0.6, 0.35)), the nose tip pushed forward at (0, 0),
    and three vertices of a prop (outside the solved region) behind it. Returns (vertices, triangles, landmarks, prop
    vertex ids)."""
    n = round(2 / STEP) + 1
    xs = np.linspace(-1, 1, n)
    gx, gy = np.meshgrid(xs, xs)
    vertices = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(n * n)])
    vertices[_grid_index(0, 0), 2] = 0.3
    triangles = []
    for j in range(n - 1):
        for i in range(n - 1):
            if eye_holes and _in_eye((xs[i] + xs[i + 1]) / 2, (xs[j] + xs[j + 1]) / 2):
                continue
            a, b, c, d = j * n + i, j * n + i + 1, (j + 1) * n + i + 1, (j + 1) * n + i
            triangles += [(a, b, c), (a, c, d)]
    prop = len(vertices) + np.arange(3)
    vertices = np.vstack([vertices, [[2, 2, -1], [2.1, 2, -1], [2, 2.1, -1]]])
    landmarks = {"nose_tip": (0, 0), "upper_lip": (0, -0.4), "lower_lip": (0, -0.5),
                 "eye_inner_left": (0.2, 0.35), "eye_outer_left": (0.6, 0.35),
                 "eye_inner_right": (-0.2, 0.35), "eye_outer_right": (-0.6, 0.35)}
    return (vertices, np.array(triangles), {k: _grid_index(*p) for k, p in landmarks.items()},
            prop)


def measure_flat(deltas, names, eye_holes=True):
    vertices, triangles, landmarks, prop = flat_face(eye_holes)
    solved = np.setdiff1d(np.arange(len(vertices)), prop)
    return em.measure_expressions(vertices, triangles, deltas, names, list(landmarks),
                                  list(landmarks.values()), solved)


def upper_lid_down(distance, side=1):
    """Deltas moving one eye's upper border row (y = 0.4 over the hole) down by `distance`."""
    vertices = flat_face()[0]
    delta = np.zeros_like(vertices)
    for x in np.arange(0.2, 0.6 + 1e-9, STEP):
        delta[_grid_index(side * x, 0.4), 1] = -distance
    return delta


def test_upper_lid_moved_down_by_the_open_height_closes_the_gap_along_the_whole_lid():
    found = measure_flat(np.stack([upper_lid_down(0.1), upper_lid_down(0.05),
                                   upper_lid_down(0.1, side=-1)]), ["shut", "half", "right"])
    assert found["shut"]["eyelid_gap_left_stations"] == pytest.approx([0.0] * 7, abs=1e-9)
    assert found["half"]["eyelid_gap_left"] == pytest.approx(0.5)
    assert found["half"]["eyelid_gap_left_stations"] == pytest.approx([0.5] * 7)
    # the other eye stays open, and the closing one is on its own side
    assert found["shut"]["eyelid_gap_right"] == pytest.approx(1.0)
    assert found["right"]["eyelid_gap_right"] == pytest.approx(0.0, abs=1e-9)
    assert found["right"]["eyelid_gap_left"] == pytest.approx(1.0)


def test_an_upper_lid_dragged_through_the_lower_one_overruns_it():
    # the upper edge moved down by one and a half open heights stands half an open height below
    # the lower edge; shut, it meets it; the other eye and a still face read 0
    found = measure_flat(np.stack([upper_lid_down(0.15), upper_lid_down(0.1),
                                   np.zeros_like(flat_face()[0])]), ["through", "shut", "still"])
    assert found["through"]["lid_overrun_left"] == pytest.approx(0.5)
    assert found["through"]["lid_overrun_right"] == 0.0
    assert found["shut"]["lid_overrun_left"] == pytest.approx(0.0, abs=1e-9)
    assert found["still"]["lid_overrun_left"] == 0.0


def test_a_lid_closed_only_in_its_middle_reads_open_at_its_ends():
    delta = np.zeros_like(flat_face()[0])
    for x in (0.35, 0.4, 0.45):            # the middle stations' neighbours only
        delta[_grid_index(x, 0.4), 1] = -0.1
    found = measure_flat(delta[None], ["middle"])["middle"]
    stations = np.array(found["eyelid_gap_left_stations"])
    assert stations[3] == pytest.approx(0.0, abs=1e-9)
    assert stations[0] == pytest.approx(1.0) and found["eyelid_gap_left"] == pytest.approx(1.0)


def test_edge_stretch_flips_and_motion_outside_have_known_answers():
    vertices, _, _, prop = flat_face()
    stretched = np.zeros_like(vertices)
    stretched[:, 0] = 2 * vertices[:, 0]                   # x three times as long
    stretched[prop] = 0.0
    # every triangle turned over: mirrored in x and flattened (the nose's sides, steep in x,
    # would keep normals within 90 degrees of their own under the mirror alone)
    mirrored = vertices * [-1, 1, 0] - vertices
    turned = np.tile([0.3, -0.2, 0.1], (len(vertices), 1))  # a shift: nothing stretched or flipped
    prop_moved = np.zeros_like(vertices)
    prop_moved[prop] = [0.0, 0.0, 0.1 * mesh.diagonal(vertices[:-3])]
    found = measure_flat(np.stack([stretched, mirrored, turned, prop_moved]),
                         ["stretched", "mirrored", "turned", "prop"])
    triangles = flat_face()[1]
    assert found["stretched"]["edge_stretch"] == pytest.approx(3.0)
    assert found["stretched"]["flipped_triangles"] == 0
    assert found["mirrored"]["flipped_triangles"] == len(triangles)
    assert found["turned"]["flipped_triangles"] == 0
    assert found["turned"]["edge_stretch"] == pytest.approx(1.0)
    assert found["prop"]["motion_outside"] == pytest.approx(0.1)
    assert found["stretched"]["motion_outside"] == 0.0


def test_excess_stretch_counts_only_what_the_clone_adds_to_the_source():
    vertices, triangles, landmarks, prop = flat_face()
    solved = np.setdiff1d(np.arange(len(vertices)), prop)
    stretched = np.zeros_like(vertices)
    stretched[:, 0] = 2 * vertices[:, 0]                   # x three times as long
    shrunk = -0.5 * vertices * [1, 0, 0]                    # x half as long
    deltas = np.stack([stretched, stretched, shrunk])
    # the source at each vertex's corresponding point: the same face, stretched by 3x in the
    # first expression (as the target), not at all in the second, shrunk in the third
    images = (vertices, np.stack([stretched, np.zeros_like(vertices), shrunk]))
    found = em.measure_expressions(vertices, triangles, deltas, ["same", "added", "shrunk"],
                                   list(landmarks), list(landmarks.values()), solved, images)
    assert found["same"]["edge_stretch"] == pytest.approx(3.0)
    assert found["same"]["excess_stretch"] == pytest.approx(1.0)
    assert found["added"]["excess_stretch"] == pytest.approx(3.0)
    assert found["shrunk"]["excess_stretch"] == pytest.approx(1.0)
    without = measure_flat(deltas[:1], ["same"])["same"]
    assert without["excess_stretch"] is None and without["excess_stretch_reason"]
    assert em.summary(found)["worst_excess_stretch"] == pytest.approx(3.0)
    assert em.summary(found)["worst_excess_stretch_expression"] == "added"


def test_excess_flips_count_only_the_turns_the_source_does_not_make():
    vertices, triangles, landmarks, prop = flat_face()
    solved = np.setdiff1d(np.arange(len(vertices)), prop)
    folded = np.zeros_like(vertices)
    folded[_grid_index(-0.8, -0.8), 0] = 3 * STEP     # one vertex pushed past its neighbours
    # the source at each vertex's corresponding point: folded alike in the first expression,
    # still in the second
    images = (vertices, np.stack([folded, np.zeros_like(vertices)]))
    found = em.measure_expressions(vertices, triangles, np.stack([folded, folded]),
                                   ["followed", "added"], list(landmarks),
                                   list(landmarks.values()), solved, images)
    assert found["followed"]["flipped_triangles"] == found["added"]["flipped_triangles"] >= 2
    assert found["followed"]["excess_flips"] == 0
    assert found["added"]["excess_flips"] == found["added"]["flipped_triangles"]
    without = measure_flat(folded[None], ["folded"])["folded"]
    assert without["excess_flips"] is None and without["excess_flips_reason"]
    summary = em.summary(found)
    assert summary["worst_excess_flips"] == found["added"]["excess_flips"]
    assert summary["worst_excess_flips_expression"] == "added"
    assert flips_phrase(summary) == (f"{summary['worst_flipped_triangles']} flipped, "
                                     f"{summary['worst_excess_flips']} beyond the source's")


def test_lip_gap_and_the_combined_jaw_open_and_mouth_close():
    vertices, _, landmarks, _ = flat_face()
    diagonal = mesh.diagonal(vertices[:-3])
    jaw = np.zeros_like(vertices)
    jaw[vertices[:, 1] <= -0.5, 1] = -0.05 * diagonal      # the lower lip and chin drop
    close = -jaw
    close[vertices[:, 1] <= -0.5, 2] = 0.01                # a push forward is no opening
    found = measure_flat(np.stack([jaw, close]), ["jawOpen", "mouthClose"])
    assert found["jawOpen"]["lip_gap"] == pytest.approx(0.05)
    assert found[em.MEASURED_TOGETHER]["lip_gap"] == pytest.approx(0.0, abs=1e-12)
    summary = em.summary(found)
    assert summary["jawOpen_lip_gap"] == pytest.approx(0.05)
    assert summary["jawOpen+mouthClose_lip_gap"] == pytest.approx(0.0, abs=1e-12)
    assert summary["eyeBlink_L_gap"] is None            # no such expression: no figure
    assert summary["worst_motion_outside"] == 0.0
    assert summary["worst_motion_outside_expression"] is None   # nothing outside moved


def test_an_eye_without_an_opening_is_none_with_a_reason():
    found = measure_flat(upper_lid_down(0.1, side=1)[None], ["shut"], eye_holes=False)["shut"]
    assert found["eyelid_gap_left"] is None and found["eyelid_gap_right"] is None
    assert "no lid edges seen" in found["eyelid_gap_left_reason"]
    assert found["lip_gap"] == 0.0                      # the lips are still measured


def test_landmarks_placed_by_hand_give_no_lid_or_lip_figures():
    vertices, triangles, landmarks, _ = flat_face()
    found = em.measure_expressions(vertices, triangles, np.zeros((1,) + vertices.shape), ["x"],
                                   [f"landmark_{k}" for k in range(len(landmarks))],
                                   list(landmarks.values()), np.unique(triangles))["x"]
    assert found["eyelid_gap_left"] is None and found["lip_gap"] is None
    assert "no landmark" in found["lip_gap_reason"]
    assert found["edge_stretch"] == 1.0 and found["flipped_triangles"] == 0


# ------------------------------------------------------------------------------ real faces

@lru_cache(maxsize=1)
def demo_head_fit_inputs():
    """(vertices, triangles, landmark names, landmark ids) of the demo head."""
    vertices, triangles = mesh.checked_triangles(data.demo_head())
    surface = Surface(vertices, triangles)
    names, ids = automatic_landmarks(vertices, triangles,
                                     face_frame(vertices, triangles, surface.search))
    return vertices, triangles, names, ids


def test_demo_head_lids_are_its_visible_lid_edges():
    # hand-checked on the demo head (MakeHuman hm08, eyes modelled as sockets): at x = 0.31 the
    # upper lid's front edge is vertex 2178 (y 7.332), the lower lid's 2221 (y 7.240); the
    # vertices behind 2178 (4216, 3105: the lid's thickness) are not its edge
    vertices, triangles, names, ids = demo_head_fit_inputs()
    openings = em.Openings(vertices, triangles, dict(zip(names, ids)))
    lids = openings.lids["eye_left"]
    assert lids.how == "seen from the front"
    assert 2178 in lids.upper and 2221 in lids.lower
    assert 4216 not in lids.upper and 3105 not in lids.upper
    assert lids.rest[3] == pytest.approx(0.0843, abs=0.002)


def test_a_coarse_lid_row_keeps_its_arch_and_drops_the_skin_above_it():
    # a coarse upper lid (rim vertices 0.2 stations apart, arching 0.2 eye widths high: each
    # stands 0.032 above its neighbours' line) and, between two of them, a vertex of the skin
    # 0.1 above the rim (what an edge triangle's nearest corner is on a decimated head)
    frame = SimpleNamespace(up=np.array([0.0, 1.0, 0.0]), forward=np.array([0.0, 0.0, 1.0]))
    opening = em._Opening(np.zeros(3), np.array([1.0, 0.0, 0.0]), frame)
    stations = np.array([0.1, 0.3, 0.5, 0.7, 0.9])
    rim = np.stack([stations, 0.8 * stations * (1 - stations), np.zeros(5)], axis=1)
    skin = [0.6, 0.8 * 0.6 * 0.4 + 0.1, 0.0]
    vertices = np.vstack([rim, skin])
    assert em._visible_edge(np.arange(6), opening, vertices, 1).tolist() == [0, 1, 2, 3, 4]
    # the same row as a lower lid (mirrored): the skin below it goes the same way
    mirrored = vertices * [1.0, -1.0, 1.0]
    assert em._visible_edge(np.arange(6), opening, mirrored, -1).tolist() == [0, 1, 2, 3, 4]


def test_a_coarse_lid_row_drops_the_skin_beside_the_edge_as_seen():
    # a coarse lower lid (rim vertices 0.25 stations apart; the edge as seen runs straight between
    # them, one mesh edge each) with, beside the rim vertex at 0.6, a vertex of the skin 0.06 eye
    # widths below that edge (a decimated head's edge triangle's nearest corner: within STANDS_OFF
    # of its neighbours' line, so the margin row keeps it), and the outer corner's vertex beyond
    # the stations seen (kept)
    frame = SimpleNamespace(up=np.array([0.0, 1.0, 0.0]), forward=np.array([0.0, 0.0, 1.0]))
    opening = em._Opening(np.zeros(3), np.array([1.0, 0.0, 0.0]), frame)
    stations = np.array([0.1, 0.35, 0.6, 0.85])
    rim = np.stack([stations, -0.8 * stations * (1 - stations), np.zeros(4)], axis=1)
    seen = np.linspace(0.05, 0.95, 200)
    edge = np.column_stack([seen, np.interp(seen, stations, rim[:, 1])])
    skin = [0.68, np.interp(0.68, stations, rim[:, 1]) - 0.06, 0.0]
    vertices = np.vstack([rim, skin, [1.0, 0.0, 0.0]])
    margin = em._visible_edge(np.arange(6), opening, vertices, -1)
    assert margin.tolist() == [0, 1, 2, 3, 4, 5]
    assert em._on_seen_edge(margin, opening, vertices, -1, edge).tolist() == [0, 1, 2, 3, 5]
    # the same row as an upper lid (mirrored)
    mirrored, mirrored_edge = vertices * [1.0, -1.0, 1.0], edge * [1.0, -1.0]
    assert em._on_seen_edge(margin, opening, mirrored, 1, mirrored_edge).tolist() == [0, 1, 2, 3, 5]


@pytest.mark.parametrize("corners", [((0.15, 0.45), (0.6, 0.45)), ((0.25, 0.3), (0.6, 0.5))])
def test_corner_landmarks_off_the_opening_give_the_lids_of_its_ends(corners):
    # a coarse game head's automatic corners can stand on its skin or lids, off the opening's
    # ends: their line above the opening (no lid seen from it), or rising across it from the
    # lower lid to the skin above (both lids seen in 49% of the measured columns: the open
    # height read 0.129 at the outer stations); both eyes moved alike, so the face's axes stay
    # level. The corners are then the opening's ends, and the lids as with the corners there
    vertices, triangles, landmarks, prop = flat_face()
    placed = em.Openings(vertices, triangles, landmarks).lids["eye_left"]
    moved = dict(landmarks)
    for side, sign in (("left", 1), ("right", -1)):
        for end, (x, y) in zip(("inner", "outer"), corners):
            moved[f"eye_{end}_{side}"] = _grid_index(sign * x, y)
    lids = em.Openings(vertices, triangles, moved).lids["eye_left"]
    pixel = 2 * em.VIEW_WIDTH / em.VIEW_PIXELS * 0.4    # two of the eye's view (0.4 wide)
    assert lids.opening.first == pytest.approx([0.2, 0.35, 0.0], abs=pixel)
    assert lids.opening.first + lids.opening.width * lids.opening.along \
        == pytest.approx([0.6, 0.35, 0.0], abs=pixel)
    assert lids.upper.tolist() == placed.upper.tolist()
    assert lids.lower.tolist() == placed.lower.tolist()
    assert lids.rest == pytest.approx(0.1, abs=pixel)
    blink = measure_flat(upper_lid_down(0.1)[None], ["blink"])["blink"]
    assert blink["eyelid_gap_left"] == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("fraction", [1.0, 0.5])
def test_demo_head_upper_lid_moved_down_by_its_middle_open_height(fraction):
    vertices, triangles, names, ids = demo_head_fit_inputs()
    lids = em.Openings(vertices, triangles, dict(zip(names, ids))).lids["eye_left"]
    opening = lids.opening
    s, h = opening.station(vertices), opening.height(vertices)
    upper_lid = (s > -0.2) & (s < 1.2) & (h > 0) & (h < opening.width)
    delta = np.zeros_like(vertices)
    delta[upper_lid] = -fraction * lids.rest[3] * opening.up
    found = em.measure_expressions(vertices, triangles, delta[None], ["lid"], names, ids,
                                   np.unique(triangles))["lid"]
    stations = np.array(found["eyelid_gap_left_stations"])
    assert stations[3] == pytest.approx(1 - fraction, abs=1e-3)
    assert stations == pytest.approx(1 - fraction * lids.rest[3] / lids.rest, abs=1e-3)
    assert found["eyelid_gap_right"] == pytest.approx(1.0)


def test_a_target_split_at_every_polygon_measures_as_the_welded_one():
    # every polygon with vertices of its own (as some exporters write a mesh): measure_clone
    # welds the copies as the fit does, so the lids are still found and read the same
    vertices, triangles, names, ids = demo_head_fit_inputs()
    head = data.demo_head()
    lids = em.Openings(vertices, triangles, dict(zip(names, ids))).lids["eye_left"]
    delta = np.zeros_like(vertices)
    delta[lids.upper] = -0.5 * lids.rest.mean() * lids.opening.up
    welded = CloneResult(["lid"], delta[None], ids, ids, names, vertices)
    corners = head.loop_vertices
    split = PolyMesh(head.vertices[corners], head.loop_totals, np.arange(len(corners)))
    first_copy = np.array([np.flatnonzero(corners == i)[0] for i in ids])
    unwelded = CloneResult(["lid"], delta[None][:, corners], ids, first_copy, names,
                           vertices)
    expected, found = em.measure_clone(head, welded)["lid"], em.measure_clone(split, unwelded)["lid"]
    assert found["eyelid_gap_left"] == pytest.approx(expected["eyelid_gap_left"], abs=1e-9)
    assert found["eyelid_gap_left_stations"] == pytest.approx(expected["eyelid_gap_left_stations"])
    assert found["edge_stretch"] == pytest.approx(expected["edge_stretch"])
    assert found["flipped_triangles"] == expected["flipped_triangles"]


@lru_cache(maxsize=1)
def library_measures():
    lib = library.load_library().subset(["eyeBlink_L", "eyeBlink_R", "jawOpen", "mouthClose"])
    vertices, triangles = mesh.checked_triangles(lib.mesh)
    face = triangles[np.all(triangles < lib.parts["face"][1], axis=1)]
    return em.measure_expressions(vertices, face, lib.deltas, lib.names,
                                  *lib.automatic_landmarks, np.unique(face))


def test_the_library_on_its_own_mesh_blinks_and_opens_its_mouth():
    found = library_measures()
    # ICT's face has eye holes, and lids with a thickness: the lids' visible edges meet
    assert found["eyeBlink_L"]["eyelid_gap_left"] < 0.1
    assert found["eyeBlink_L"]["eyelid_gap_right"] == pytest.approx(1.0, abs=0.01)
    assert found["eyeBlink_R"]["eyelid_gap_right"] < 0.1
    assert found["eyeBlink_R"]["eyelid_gap_left"] == pytest.approx(1.0, abs=0.01)
    jaw = found["jawOpen"]["lip_gap"]
    assert jaw > 0.03
    assert abs(found[em.MEASURED_TOGETHER]["lip_gap"]) < 0.25 * jaw
    for row in found.values():
        assert np.isfinite(row["edge_stretch"]) and row["flipped_triangles"] >= 0


def test_makehuman_blinks_on_its_own_topology(shared_data):
    folder = shared_data / "makehuman-head"
    neutral = mesh.read_obj(folder / "neutral.obj")
    vertices, triangles = mesh.checked_triangles(neutral)
    surface = Surface(vertices, triangles)
    names, ids = automatic_landmarks(vertices, triangles,
                                     face_frame(vertices, triangles, surface.search))
    expressions = ["eye-left-closure", "eye-right-closure", "mouth-open"]
    deltas = np.stack([mesh.read_obj(folder / f"{name}.obj").vertices - vertices
                       for name in expressions])
    found = em.measure_expressions(vertices, triangles, deltas, expressions, names, ids,
                                   np.unique(triangles))
    # MakeHuman's own blink closes the lids along the whole lid: the upper lid's edge ends a
    # little below the lower one's at every station (-0.13 of the open height at the most open)
    for name, side in (("eye-left-closure", "left"), ("eye-right-closure", "right")):
        assert -0.3 < found[name][f"eyelid_gap_{side}"] < 0.0
    assert found["eye-left-closure"]["eyelid_gap_right"] == pytest.approx(1.0, abs=1e-6)
    assert found["eye-right-closure"]["eyelid_gap_left"] == pytest.approx(1.0, abs=1e-6)
    assert found["mouth-open"]["lip_gap"] > 0.03


@lru_cache(maxsize=1)
def demo_head_clone():
    """(the library's four measured expressions, the demo head, their clone onto it)."""
    lib = library.load_library().subset(["eyeBlink_L", "eyeBlink_R", "jawOpen", "mouthClose"])
    head = data.demo_head()
    return lib, head, clone_expressions(lib.mesh, lib.deltas, lib.names, head,
                                        source_landmarks=lib.automatic_landmarks,
                                        source_modes=lib.shape_modes)


def test_a_real_clone_onto_the_demo_head_is_measured():
    lib, head, result = demo_head_clone()
    found = em.measure_clone(head, result, source=lib.mesh, source_deltas=lib.deltas)
    print("\nlibrary onto the demo head:", {name: {key: row[key] for key in (
        "eyelid_gap_left", "eyelid_gap_right", "lip_gap", "edge_stretch", "excess_stretch",
        "flipped_triangles", "excess_flips")} for name, row in found.items()})
    assert set(found) == set(lib.names) | {em.MEASURED_TOGETHER}
    for row in found.values():
        for key in ("eyelid_gap_left", "eyelid_gap_right", "lip_gap", "edge_stretch",
                    "motion_outside"):
            assert np.isfinite(row[key]), key
    # what the current engine demonstrably does: the blink stays on its own side
    assert found["eyeBlink_L"]["eyelid_gap_right"] == pytest.approx(1.0, abs=0.1)
    assert found["eyeBlink_R"]["eyelid_gap_left"] == pytest.approx(1.0, abs=0.1)
    # the rims' positional goals (core.rims) bring a closing eye's rows together: measured 0.5%
    # (left) and 0.5% (right) of the open height left (ICT's own blink leaves 8-10% at the inner
    # station; the station goals alone left 7.1% and 6.3%, the goals at the rims' images 2.0% and
    # 5.2%, no goals 15.6% and 16.6%); the bar is 10% along the lid
    assert found["eyeBlink_L"]["eyelid_gap_left"] < 0.1
    assert found["eyeBlink_R"]["eyelid_gap_right"] < 0.1
    assert found["jawOpen"]["lip_gap"] > 0.01
    # the jawOpen bars: no edge stretched more than 2.5x beyond the source's own stretch
    # (measured 1.64x; the blinks 1.69x / 1.44x) and no triangle turned over where the source's
    # jawOpen does not turn it or one beside it over (none turned over at all)
    for name in ("jawOpen", "eyeBlink_L", "eyeBlink_R"):
        assert found[name]["excess_stretch"] <= 2.5
    assert found["jawOpen"]["excess_flips"] == 0
    # and at jawOpen + mouthClose the lips sealed: no more than 0.2% of the diagonal further apart
    # than at rest (measured -1.18%: pressed together past rest, as the library's own do)
    assert found[em.MEASURED_TOGETHER]["lip_gap"] <= 0.002
    summary = em.summary(found)
    assert summary["eyeBlink_L_gap"] == found["eyeBlink_L"]["eyelid_gap_left"]
    assert summary["worst_edge_stretch"] == max(row["edge_stretch"] for row in found.values())
    clause = measures_clause(summary)
    assert clause.startswith("blink gap L ") and "flipped" in clause
    # measured beside the source: the clause reads the excess stretch, not the raw one
    assert f"stretch {summary['worst_excess_stretch']:.1f}x the source's" in clause


def test_a_lip_vertex_left_behind_breaks_the_stretch_bar():
    """The issue's "lips keep their seam (no lip vertex left behind while its neighbours move)"
    is read by the stretch beyond the source's own: the demo head's jawOpen as cloned (1.64x,
    under the bar of 2.5x), then with one lip vertex held still while the rest of the lip moves
    as cloned (the torn lip the issue saw): its edges stretch past the bar (measured 19.4x, and 2
    triangles turned over beyond the source's)."""
    lib, head, result = demo_head_clone()
    jaw = result.names.index("jawOpen")
    lower_lip = result.target_landmarks[result.landmark_names.index("lower_lip")]
    torn = result.deltas[jaw].copy()
    torn[lower_lip] = 0.0
    found = em.measure_clone(head, result, ["jawOpen", "torn"],
                             np.stack([result.deltas[jaw], torn]), source=lib.mesh,
                             source_deltas=lib.deltas[[lib.names.index("jawOpen")] * 2])
    assert found["jawOpen"]["excess_stretch"] <= 2.5
    assert found["torn"]["excess_stretch"] > 2.5 and found["torn"]["excess_flips"] > 0


def test_the_library_lids_leave_out_its_sockets():
    """On the library's region as a fit takes it (the parts holding its landmarks: the face and
    its eye sockets), no lid vertex is a socket wall seen through the opening: every one lies
    near the corners' line in depth, and the blink's lids cross by no more than ICT's own (a
    socket vertex in the lower row read the left blink's outer lids as crossing by 38%)."""
    lib = library.load_library().subset(["eyeBlink_L", "eyeBlink_R"])
    welded, index = mesh.welded(lib.mesh)
    first = np.unique(index, return_index=True)[1]
    vertices, triangles = mesh.checked_triangles(welded, "library")
    names, ids = lib.automatic_landmarks
    landmarks = index[np.asarray(ids)]
    region = Surface(vertices, triangles).parts_holding(landmarks)
    openings = em.Openings(vertices, region.triangles,
                           {str(n): int(i) for n, i in zip(names, landmarks)})
    for lids in openings.lids.values():
        for row in (lids.upper, lids.lower):
            depth = lids.opening.depth(vertices[row])
            assert depth.min() > -em.LID_DEPTH * lids.opening.width, depth.min()
    found = em.measure_expressions(vertices, region.triangles, lib.deltas[:, first], lib.names,
                                   names, landmarks, region.used)
    for name, side in (("eyeBlink_L", "left"), ("eyeBlink_R", "right")):
        stations = found[name][f"eyelid_gap_{side}_stations"]
        assert max(stations) < 0.1 and min(stations) > -0.2, (name, stations)


def test_close_ups_show_the_expressions_that_close_an_eye_and_open_the_mouth_furthest():
    measures = {
        "blink": {"eyelid_gap_left": 0.08, "eyelid_gap_right": 1.0, "lip_gap": 0.0},
        "squint": {"eyelid_gap_left": 0.6, "eyelid_gap_right": 0.6, "lip_gap": 0.001},
        "open": {"eyelid_gap_left": 1.0, "eyelid_gap_right": 1.0, "lip_gap": 0.05},
        "smile": {"eyelid_gap_left": None, "eyelid_gap_right": 0.9, "lip_gap": 0.004},
    }
    assert em.close_up_expressions(measures, list(measures)) == ("blink", "open")
    # only among the names given (the keys written); none closes or opens enough: None
    assert em.close_up_expressions(measures, ["squint", "smile"]) == (None, None)
    assert em.close_up_expressions({}, []) == (None, None)
