"""Cloning quality on real faces (bundled data only; the figures are printed, run with -s).

1. Same face, new topology, moved, with a known answer (blender_tests/ground_truth.py): the ICT
   face region with its expressions cloned onto a remesh of itself under a random similarity.
   Bars: relative error ||clone - truth||_F / ||truth||_F (all target vertices, no offset
   removed) <= 5% on average and <= 15% for every expression; registration mean surface distance
   <= 0.3% of the target's diagonal. Beside it, the same figure from the TRUE registration (the
   source moved by the similarity, core.cloning.fit_registered): the error of correspondence and
   transfer alone, with the engine's vertex map and with the method's centroid pairs.
2. ICT face onto the MakeHuman head (the bundled demo head): registration <= 0.5% of the head's
   diagonal, and the key expressions do what their names say, measured at the hand-checked
   fixture vertices.
"""
import json

import numpy as np
import pytest

from blender_tests.helpers.paths import FIXTURES
from blender_tests.helpers import ground_truth as gt
from exclone_addon.core import data, deformation
from exclone_addon.core.cloning import (CloneSettings, clone_expressions, fit_registered,
                                        transfer_expressions)
from exclone_addon.core.library import load_library
from exclone_addon.core.mesh import PolyMesh, read_obj

DEMO_HEAD = data.DEMO_HEAD_FILE

MEAN_ERROR_BAR = 0.05
MAX_ERROR_BAR = 0.15
KNOWN_CASE_REGISTRATION_BAR = 0.003
HEAD_REGISTRATION_BAR = 0.005
# An expression whose truth on the face region is below this share of the largest one has no
# scale to measure a relative error against: ICT's PupilDilate_L/_R move the eyeballs, which are
# not in the face region (on it: exactly 0, and 4e-5 of jawOpen's size respectively).
NEGLIGIBLE = 1e-3
# The key expressions on MakeHuman must move at least half as much as the source does, relative
# to the same feature (mouth width, eye fissure width), measured on ICT at its fixture vertices.
MOTION_SHARE = 0.5
# "Barely moves": the other side, relative to the same feature size.
STILL = 0.05


@pytest.fixture(scope="module")
def library():
    return load_library()


@pytest.fixture(scope="module")
def landmark_fixtures():
    return {name: {k: v["vertex"] for k, v in json.loads((FIXTURES / f"{name}_landmarks.json")
                                                         .read_text())["landmarks"].items()}
            for name in ("ict", "makehuman")}


def with_zero(names, deltas):
    """The expressions plus an all-zero one named "zero"."""
    return list(names) + ["zero"], np.concatenate([deltas, np.zeros((1,) + deltas.shape[1:])])


@pytest.fixture(scope="module")
def known_case(library):
    """The remeshed, moved ICT face region and its exact expressions, plus the source region."""
    lib = library
    case = gt.make_case(lib.mesh.vertices, (lib.mesh.loop_totals, lib.mesh.loop_vertices),
                        lib.names, lib.deltas, seed=0, landmarks68=lib.landmarks68)
    neutral, triangles = gt.face_region(lib.mesh.vertices, lib.mesh.loop_totals,
                                        lib.mesh.loop_vertices)
    names, deltas = with_zero(lib.names, lib.deltas[:, : gt.ICT_FACE_VERTEX_COUNT])
    case["source"] = PolyMesh.from_faces(neutral, triangles)
    case["source_deltas"] = deltas
    case["clone_names"] = names
    case["truth"] = np.concatenate([case["truth_deltas"],
                                    np.zeros((1,) + case["truth_deltas"].shape[1:])])
    return case


def clone_known(case, landmarks=None, formulation="reduced"):
    return clone_expressions(case["source"], case["source_deltas"], case["clone_names"],
                             case["target_mesh"], landmarks=landmarks,
                             settings=CloneSettings(formulation=formulation))


@pytest.fixture(scope="module")
def automatic_clone(known_case):
    return clone_known(known_case)


@pytest.fixture(scope="module")
def true_landmark_clone(known_case):
    """The 68 iBUG vertices of the source and the nearest target vertex to each true image."""
    return clone_known(known_case, {"source": known_case["source_landmarks"],
                                    "target": known_case["target_landmarks"]})


@pytest.fixture(scope="module")
def true_registration_clones(known_case):
    """Transfers from the TRUE registration (the source moved by the case's similarity), so the
    error left is the correspondence's and the transfer's alone: with the vertex map (the
    engine's) and with the method's centroid pairs only."""
    exact = gt.apply_similarity(known_case["source"].vertices, *known_case["similarity"])
    return {scheme: transfer_expressions(
                fit_registered(known_case["source"], known_case["target_mesh"], exact,
                               settings=CloneSettings(correspondence=scheme)),
                known_case["source_deltas"], known_case["clone_names"])
            for scheme in ("vertex", "triangle")}


def error_figures(deltas, truth, names):
    """(per-expression relative errors over the measurable expressions, negligible names)."""
    sizes = np.linalg.norm(truth.reshape(len(truth), -1), axis=1)
    measurable = sizes > NEGLIGIBLE * sizes.max()
    errors = gt.relative_error(deltas[measurable], truth[measurable])
    return dict(zip([n for n, m in zip(names, measurable) if m], errors)), \
        [n for n, m in zip(names, measurable) if not m]


@pytest.fixture(scope="module")
def known_figures(known_case, automatic_clone, true_landmark_clone, true_registration_clones):
    truth, names = known_case["truth"], known_case["clone_names"]
    runs = {"automatic landmarks": automatic_clone.deltas,
            "68 true landmark pairs": true_landmark_clone.deltas,
            "true registration, vertex map": true_registration_clones["vertex"].deltas,
            "true registration, centroid pairs": true_registration_clones["triangle"].deltas}
    figures = {run: error_figures(d, truth, names)[0] for run, d in runs.items()}
    # where the registered source should be: the source moved by the case's own similarity
    R, s, t = known_case["similarity"]
    source = known_case["source"]
    exact = gt.apply_similarity(source.vertices, R, s, t)
    region = np.unique(source.triangles())
    diagonal = np.linalg.norm(np.ptp(known_case["target_vertices"], axis=0))
    print("\nknown-answer case: relative error per expression (" + " / ".join(runs) + ")")
    for name in figures["automatic landmarks"]:
        print(f"  {name:18s} " + " ".join(f"{100 * figures[run][name]:7.2f}%" for run in runs))
    for run, clone in (("automatic landmarks", automatic_clone),
                       ("68 true landmark pairs", true_landmark_clone)):
        q = clone.quality
        slide = np.linalg.norm(clone.registered_source[region] - exact[region], axis=1) / diagonal
        print(f"  {run}: registration {100 * q['registration_mean_distance_rel']:.3f}% of the "
              f"diagonal from the surface, {100 * slide.mean():.2f}% (max {100 * slide.max():.2f}%) "
              f"from the true position, valid {q['registration_valid_fraction']:.3f}, coverage "
              f"{q['correspondence_coverage']:.3f}, {q['landmark_count']} landmarks, "
              f"{clone.timings['total']:.1f} s")
    for run in runs:
        values = np.array(list(figures[run].values()))
        worst = max(figures[run], key=figures[run].get)
        print(f"  {run}: mean {100 * values.mean():.2f}%, max {100 * values.max():.2f}% ({worst})")
    return figures


def assert_error_bars(errors):
    values = np.array(list(errors.values()))
    over = {n: f"{100 * e:.1f}%" for n, e in errors.items() if not e <= MAX_ERROR_BAR}
    assert values.mean() <= MEAN_ERROR_BAR and not over, (
        f"mean relative error {100 * values.mean():.2f}% (bar {100 * MEAN_ERROR_BAR:.0f}%); "
        f"{len(over)} expressions above {100 * MAX_ERROR_BAR:.0f}%: {over}")


def test_known_answer_with_automatic_landmarks(known_figures):
    assert_error_bars(known_figures["automatic landmarks"])


# From the true registration, the vertex map's error (measured 0.96% mean) is what correspondence
# and transfer cost by themselves; the method's centroid pairs cost 4.4% there.
TRUE_REGISTRATION_BAR = 0.015


def test_true_registration_isolates_the_correspondence_error(known_figures):
    vertex = np.mean(list(known_figures["true registration, vertex map"].values()))
    centroid = np.mean(list(known_figures["true registration, centroid pairs"].values()))
    assert vertex <= TRUE_REGISTRATION_BAR, f"vertex map, true registration: {100 * vertex:.2f}%"
    assert vertex < 0.5 * centroid, (f"vertex map {100 * vertex:.2f}% vs centroid pairs "
                                     f"{100 * centroid:.2f}%: the vertex map should halve it")


def test_known_answer_registration_lies_on_the_target(automatic_clone):
    distance = automatic_clone.quality["registration_mean_distance_rel"]
    assert distance <= KNOWN_CASE_REGISTRATION_BAR, f"{100 * distance:.3f}% of the diagonal"


def test_known_answer_negligible_expressions_stay_negligible(known_case, automatic_clone):
    truth, names = known_case["truth"], known_case["clone_names"]
    _, negligible = error_figures(automatic_clone.deltas, truth, names)
    assert set(negligible) == {"PupilDilate_L", "PupilDilate_R", "zero"}
    largest = np.linalg.norm(truth.reshape(len(truth), -1), axis=1).max()
    for name in negligible:
        k = names.index(name)
        error = np.linalg.norm(automatic_clone.deltas[k] - truth[k])
        assert error <= NEGLIGIBLE * largest, f"{name}: error {error:.3g} vs largest {largest:.3g}"


@pytest.fixture(scope="module")
def head_clones(library):
    """The whole ICT library (head, eyes, teeth... as shipped) cloned onto the demo head, lazily
    per formulation."""
    head = read_obj(DEMO_HEAD)
    names, deltas = with_zero(library.names, library.deltas)
    cache = {}

    def get(formulation):
        if formulation not in cache:
            cache[formulation] = clone_expressions(library.mesh, deltas, names, head,
                                                   settings=CloneSettings(formulation=formulation))
            q = cache[formulation].quality
            print(f"\n[MakeHuman {formulation}] registration "
                  f"{100 * q['registration_mean_distance_rel']:.3f}% of the diagonal, valid "
                  f"{q['registration_valid_fraction']:.3f}, coverage "
                  f"{q['correspondence_coverage']:.3f}, {cache[formulation].timings['total']:.1f} s")
        return cache[formulation]

    return np.asarray(head.vertices, dtype=np.float64), get


def motion_ratios(vertices, deltas_of, ids):
    """Feature motions relative to feature sizes at fixture vertices `ids` (name -> vertex)."""
    p = lambda name: vertices[ids[name]]   # noqa: E731
    mouth = np.linalg.norm(p("mouth_corner_left") - p("mouth_corner_right"))
    fissure = {side: np.linalg.norm(p(f"eye_inner_{side}") - p(f"eye_outer_{side}"))
               for side in ("left", "right")}
    jaw, blink, smile = deltas_of("jawOpen"), deltas_of("eyeBlink_L"), deltas_of("mouthSmile_L")
    upper_y = jaw[ids["upper_lip"], 1]
    return {
        "jawOpen lips part / mouth width": (upper_y - jaw[ids["lower_lip"], 1]) / mouth,
        "jawOpen chin down vs upper lip / mouth width": (upper_y - jaw[ids["chin"], 1]) / mouth,
        "eyeBlink_L left upper lid down / fissure": -blink[ids["eyelid_upper_left"], 1] / fissure["left"],
        "eyeBlink_L right upper lid |move| / fissure":
            np.linalg.norm(blink[ids["eyelid_upper_right"]]) / fissure["right"],
        "mouthSmile_L left corner |move| / mouth width":
            np.linalg.norm(smile[ids["mouth_corner_left"]]) / mouth,
        "mouthSmile_L right corner |move| / mouth width":
            np.linalg.norm(smile[ids["mouth_corner_right"]]) / mouth,
        "mouthSmile_L left corner direction": smile[ids["mouth_corner_left"]]
        / max(np.linalg.norm(smile[ids["mouth_corner_left"]]), 1e-300),
    }


@pytest.fixture(scope="module")
def source_motion(library, landmark_fixtures):
    return motion_ratios(library.mesh.vertices, lambda n: library.deltas[library.names.index(n)],
                         landmark_fixtures["ict"])


@pytest.mark.parametrize("formulation", deformation.FORMULATIONS)
def test_head_registration_lies_on_the_head(head_clones, formulation):
    distance = head_clones[1](formulation).quality["registration_mean_distance_rel"]
    assert distance <= HEAD_REGISTRATION_BAR, f"{100 * distance:.3f}% of the diagonal"


@pytest.mark.parametrize("formulation", deformation.FORMULATIONS)
def test_head_outputs_are_finite_and_zero_stays_zero(head_clones, formulation):
    vertices, get = head_clones
    result = get(formulation)
    assert result.deltas.shape == (len(result.names), len(vertices), 3)
    assert np.isfinite(result.deltas).all() and np.isfinite(result.registered_source).all()
    assert np.abs(result.deltas[result.names.index("zero")]).max() < 1e-12


def test_known_answer_outputs_are_finite_and_zero_stays_zero(automatic_clone, true_landmark_clone):
    for result in (automatic_clone, true_landmark_clone):
        assert np.isfinite(result.deltas).all() and np.isfinite(result.registered_source).all()
        assert np.abs(result.deltas[result.names.index("zero")]).max() < 1e-12


@pytest.mark.parametrize("formulation", deformation.FORMULATIONS)
def test_head_key_expressions_do_what_they_say(head_clones, source_motion, landmark_fixtures,
                                               formulation):
    vertices, get = head_clones
    result = get(formulation)
    cloned = motion_ratios(vertices, lambda n: result.deltas[result.names.index(n)],
                           landmark_fixtures["makehuman"])
    print(f"\n[MakeHuman {formulation}] motion (clone vs ICT source):")
    for name, value in cloned.items():
        print(f"  {name:48s} {np.round(value, 3)}  vs  {np.round(source_motion[name], 3)}")
    problems = []
    for name in ("jawOpen lips part / mouth width", "jawOpen chin down vs upper lip / mouth width",
                 "eyeBlink_L left upper lid down / fissure",
                 "mouthSmile_L left corner |move| / mouth width"):
        if not cloned[name] >= MOTION_SHARE * source_motion[name]:
            problems.append(f"{name}: {cloned[name]:.3f} < {MOTION_SHARE} x source "
                            f"{source_motion[name]:.3f}")
    for name in ("eyeBlink_L right upper lid |move| / fissure",
                 "mouthSmile_L right corner |move| / mouth width"):
        if not cloned[name] <= STILL:
            problems.append(f"{name}: {cloned[name]:.3f} > {STILL}")
    # the smiling corner goes out (+x, the character's left), up (+y) and back (-z)
    direction = cloned["mouthSmile_L left corner direction"]
    if not (direction[0] > 0.25 and direction[1] > 0.25 and direction[2] < -0.25):
        problems.append(f"mouthSmile_L left corner direction {np.round(direction, 2)} is not "
                        "out, up and back (each component > 0.25)")
    assert not problems, "; ".join(problems)
