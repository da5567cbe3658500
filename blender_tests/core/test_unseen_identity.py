"""Registration onto a face the engine has never seen, with a known answer (issue #10 item 2).

A new ICT identity (the shared identity model, weights drawn from a standard normal with a
seed), its face region remeshed to another topology (about 7,000 vertices) and moved by a random
similarity (blender_tests/helpers/ground_truth.py). The bundled library's face region is cloned
onto it with AUTOMATIC landmarks and the library's shape modes (the identity model's first 30,
which it ships: the registration starts from the face of that space nearest the target, as a
user's clone from the library does). Known: where every source vertex
belongs on the target (the identity's own vertex, moved) and every expression's true motion.

- correspondence error: each registered source vertex against its true place, / the target's
  bounding-box diagonal: mean and 95th percentile over the face region;
- transfer error: ||clone - truth||_F / ||truth||_F, averaged over the measurable expressions,
  against the same engine's from the exact registration (cloning.fit_registered with the
  clone's landmarks, so the eyelid rims close the lids there too); and, the rims left out of
  both, the engine's registration against the exact one (the registration's share alone);
- the blinks (issue #10 item 1, core.expression_measures): each eyeBlink's remaining gap, a share
  of the eye's open height, on its own side, and the other eye's.

The bars are asserted, and what is reached with a small margin (seeds 1 and 2: two faces, so
the figures are not one face's).
"""
import numpy as np
import pytest

from blender_tests.helpers import ground_truth as gt
from blender_tests.helpers.paths import SHARED_DATA
from exclone_addon.core.cloning import (clone_expressions, fit_faces, fit_registered,
                                        transfer_expressions)
from exclone_addon.core.expression_measures import BLINKS, MEASURED_TOGETHER, measure_clone
from exclone_addon.core.library import load_library
from exclone_addon.core.mesh import PolyMesh, diagonal

IDENTITIES = SHARED_DATA / "ict-facekit" / "identities.npz"

pytestmark = pytest.mark.skipif(not IDENTITIES.exists(),
                                reason=f"needs the shared ICT identity model ({IDENTITIES})")

# The bars: correspondence mean and 95th percentile (x target diagonal), and the
# transfer error against the exact registration's.
MEAN_BAR, P95_BAR, RATIO_BAR = 0.003, 0.008, 1.3

# Reached (measured in both venvs, numpy 1.26 and 2), checked with a 10% margin:
# seed -> (mean, 95th percentile, transfer error / the same engine's from the exact registration,
# the same two without their eyelid rims). From the library's neutral rather than its shape
# space's nearest face the registration slid along the surface: 0.58% / 1.17% mean, 1.68% /
# 3.02% 95th percentile, 1.79x / 1.79x without the rims. The rims close lids that the truth (the
# library's deltas added to the identity's face) leaves 32-44% open, from either registration
# alike: the exact registration's error without them was the ratio's base before (2.75x / 2.11x).
REACHED = {1: (0.0011, 0.0027, 1.02, 1.28), 2: (0.0009, 0.0021, 1.11, 1.16)}
MARGIN = 1.1
# The blinks' remaining gap (x the open height) on the closing eye, reached (checked within
# BLINK_MARGIN), and the bar; the other eye stays open (its gap at least OTHER_OPEN). The
# source's own blinks leave 0.079 / 0.085 at the inner station (0.2 of the width); matched to it
# linearly (the rows' motions up alone, not their slide along the opening) the clones left 0.121
# / 0.108 (seed 1) and 0.102 / 0.115 (seed 2) there; now the rows meet where the source's do.
BLINK_REACHED = {1: {"eyeBlink_L": 0.004, "eyeBlink_R": 0.009},
                 2: {"eyeBlink_L": 0.007, "eyeBlink_R": 0.003}}
BLINK_MARGIN = 0.01
BLINK_BAR, OTHER_OPEN = 0.1, 0.95
# The shape modes the registration starts from when the face is drawn beyond them.
BEYOND = 20


@pytest.fixture(scope="module")
def library():
    return load_library()


@pytest.fixture(scope="module", params=sorted(REACHED), ids=lambda seed: f"seed{seed}")
def identity(request, library):
    """The measured clone of one identity: {seed, mean, p95, ratio, registration_ratio,
    text}."""
    seed = request.param
    with np.load(IDENTITIES) as model:
        modes = model["deltas"].astype(np.float64)
    weights = np.random.default_rng(seed).standard_normal(len(modes))
    face = library.mesh.vertices + np.tensordot(weights, modes, 1)
    polygons = (library.mesh.loop_totals, library.mesh.loop_vertices)
    case = gt.make_case(face, polygons, library.names, library.deltas, seed=seed)
    neutral, triangles = gt.face_region(library.mesh.vertices, *polygons)
    source = PolyMesh.from_faces(neutral, triangles)
    deltas = library.deltas[:, :len(neutral)]
    target, truth = case["target_mesh"], case["truth_deltas"]

    clone = clone_expressions(source, deltas, library.names, target,
                              source_modes=library.shape_modes[:, :len(neutral)])
    exact = gt.apply_similarity(face[:len(neutral)], *case["similarity"])
    region = np.unique(triangles)
    error = np.linalg.norm(clone.registered_source[region] - exact[region], axis=1) \
        / diagonal(target.vertices)
    # the same engine from the exact registration: the clone's landmarks, so its eyelid rims,
    # kept; and both registrations without them (the registration's share alone)
    marks = (clone.landmark_names, clone.source_landmarks, clone.target_landmarks)
    error_of = {name: float(np.nanmean(gt.relative_error(transfer_expressions(
        fit_registered(source, target, registered, landmarks=landmarks), deltas,
        library.names).deltas, truth)))
        for name, registered, landmarks in (("best", exact, marks), ("exact", exact, None),
                                            ("registration", clone.registered_source, None))}
    engine = float(np.nanmean(gt.relative_error(clone.deltas, truth)))
    best, registration = error_of["best"], error_of["registration"]
    measures = measure_clone(target, clone, source=source, source_deltas=deltas)
    # the face drawn from all 30 modes, the registration started from the first BEYOND only: a
    # face the shape space cannot make exactly
    beyond = fit_faces(source, target,
                       source_modes=library.shape_modes[:BEYOND, :len(neutral)]).registered_source
    beyond_error = np.linalg.norm(beyond[region] - exact[region], axis=1) \
        / diagonal(target.vertices)
    figures = {"seed": seed, "mean": float(error.mean()),
               "p95": float(np.quantile(error, 0.95)), "ratio": engine / best,
               "registration_ratio": registration / error_of["exact"],
               "shape_start": clone.quality["shape_space_start"],
               "beyond": (float(beyond_error.mean()), float(np.quantile(beyond_error, 0.95))),
               "blinks": {name: (measures[name][f"eyelid_gap_{closing}"],
                                 measures[name][f"eyelid_gap_{other}"])
                          for name, (closing, other) in BLINKS.items()},
               "jaw": {key: measures["jawOpen"][key]
                       for key in ("lip_gap", "excess_stretch", "excess_flips")},
               "sealed": measures[MEASURED_TOGETHER]["lip_gap"]}
    figures["text"] = (f"seed {seed}: correspondence mean {100 * figures['mean']:.2f}%, "
                       f"95th percentile {100 * figures['p95']:.2f}% of the diagonal; transfer "
                       f"error {engine:.3f} against {best:.3f} from the exact registration "
                       f"({figures['ratio']:.2f}x; without the eyelid rims, both "
                       f"{figures['registration_ratio']:.2f}x); "
                       f"{clone.quality['landmark_count']} landmarks; from {BEYOND} modes: "
                       f"mean {100 * figures['beyond'][0]:.2f}%, 95th percentile "
                       f"{100 * figures['beyond'][1]:.2f}%; blinks (closing eye's gap, "
                       f"the other's) {figures['blinks']}; jawOpen {figures['jaw']}, "
                       f"sealed {figures['sealed']:.4f}")
    return figures


def test_the_registration_reaches_what_it_reached(identity):
    print("\n" + identity["text"])
    mean, p95, ratio, registration_ratio = REACHED[identity["seed"]]
    assert identity["shape_start"], identity["text"]      # a face of the library's space
    assert identity["mean"] <= MARGIN * mean, identity["text"]
    assert identity["p95"] <= MARGIN * p95, identity["text"]
    assert identity["ratio"] <= MARGIN * ratio, identity["text"]
    assert identity["registration_ratio"] <= MARGIN * registration_ratio, identity["text"]


def test_both_blinks_are_measured_and_close(identity):
    for name, (gap, other) in identity["blinks"].items():
        assert gap is not None and other is not None, identity["text"]
        assert gap <= BLINK_REACHED[identity["seed"]][name] + BLINK_MARGIN, identity["text"]
        assert other >= OTHER_OPEN, identity["text"]


def test_blinks_meet_the_bar(identity):
    assert all(gap <= BLINK_BAR for gap, _ in identity["blinks"].values()), identity["text"]


def test_the_mouth_meets_the_bars(identity):
    """The issue's jawOpen bars on the new faces: the lips part, no edge stretched more than 2.5x
    beyond the source's own stretch, no triangle turned over beyond the source's turns
    (measured 1.27x / 1.30-1.31x, none, seeds 1 / 2), and at jawOpen + mouthClose the lips
    sealed: no more than 0.2% of the diagonal further apart than at rest (-0.86% / -0.43%)."""
    jaw = identity["jaw"]
    assert jaw["lip_gap"] > 0.01, identity["text"]
    assert jaw["excess_stretch"] <= 2.5 and jaw["excess_flips"] == 0, identity["text"]
    assert identity["sealed"] <= 0.002, identity["text"]


def test_correspondence_meets_the_bars(identity):
    assert identity["mean"] <= MEAN_BAR and identity["p95"] <= P95_BAR, identity["text"]


def test_a_face_beyond_the_shape_modes_meets_the_bars(identity):
    mean, p95 = identity["beyond"]
    assert mean <= MEAN_BAR and p95 <= P95_BAR, identity["text"]


def test_transfer_error_is_near_the_exact_registrations(identity):
    assert identity["ratio"] <= RATIO_BAR, identity["text"]
