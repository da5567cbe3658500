"""Registration onto a face the engine has never seen, with a known answer (issue #10 item 2).

A new ICT identity (the shared identity model, weights drawn from a standard normal with a
seed), its face region remeshed to another topology (about 7,000 vertices) and moved by a random
similarity (blender_tests/helpers/ground_truth.py). The bundled library's face region is cloned
onto it with AUTOMATIC landmarks, as a user's clone would be. Known: where every source vertex
belongs on the target (the identity's own vertex, moved) and every expression's true motion.

- correspondence error: each registered source vertex against its true place, / the target's
  bounding-box diagonal: mean and 95th percentile over the face region;
- transfer error: ||clone - truth||_F / ||truth||_F, averaged over the measurable expressions,
  against the same engine's from the exact registration (cloning.fit_registered).

The issue's bars are kept as strict xfails carrying the measured figures; what is reached is
asserted with a small margin (seeds 1 and 2: two faces, so the figures are not one face's).
"""
import numpy as np
import pytest

from blender_tests.helpers import ground_truth as gt
from blender_tests.helpers.paths import SHARED_DATA
from exclone_addon.core.cloning import clone_expressions, fit_registered, transfer_expressions
from exclone_addon.core.library import load_library
from exclone_addon.core.mesh import PolyMesh, diagonal

IDENTITIES = SHARED_DATA / "ict-facekit" / "identities.npz"

pytestmark = pytest.mark.skipif(not IDENTITIES.exists(),
                                reason=f"needs the shared ICT identity model ({IDENTITIES})")

# The bars: correspondence mean and 95th percentile (x target diagonal), and the
# transfer error against the exact registration's.
MEAN_BAR, P95_BAR, RATIO_BAR = 0.003, 0.008, 1.3

# Reached (measured in both venvs, numpy 1.26 and 2; the transfer error's ratio moved between
# 1.72x and 1.80x on seed 1 with the eyelid rims' changes), checked with a 10% margin:
# seed -> (mean, 95th percentile, transfer error / exact registration's, the same through
# fit_registered from the engine's registration: its landmarks, so its eyelid rims, left out).
REACHED = {1: (0.0058, 0.0168, 1.80, 1.79), 2: (0.0117, 0.0302, 2.89, 1.79)}
MARGIN = 1.1


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

    clone = clone_expressions(source, deltas, library.names, target)
    exact = gt.apply_similarity(face[:len(neutral)], *case["similarity"])
    region = np.unique(triangles)
    error = np.linalg.norm(clone.registered_source[region] - exact[region], axis=1) \
        / diagonal(target.vertices)
    exact_clone, registration_only = (
        transfer_expressions(fit_registered(source, target, registered), deltas, library.names)
        for registered in (exact, clone.registered_source))
    engine = float(np.nanmean(gt.relative_error(clone.deltas, truth)))
    best = float(np.nanmean(gt.relative_error(exact_clone.deltas, truth)))
    registration = float(np.nanmean(gt.relative_error(registration_only.deltas, truth)))
    figures = {"seed": seed, "mean": float(error.mean()),
               "p95": float(np.quantile(error, 0.95)), "ratio": engine / best,
               "registration_ratio": registration / best}
    figures["text"] = (f"seed {seed}: correspondence mean {100 * figures['mean']:.2f}%, "
                       f"95th percentile {100 * figures['p95']:.2f}% of the diagonal; transfer "
                       f"error {engine:.3f} against {best:.3f} from the exact registration "
                       f"({figures['ratio']:.2f}x; the registration alone "
                       f"{figures['registration_ratio']:.2f}x); "
                       f"{clone.quality['landmark_count']} landmarks")
    return figures


def test_the_registration_reaches_what_it_reached(identity):
    mean, p95, ratio, registration_ratio = REACHED[identity["seed"]]
    assert identity["mean"] <= MARGIN * mean, identity["text"]
    assert identity["p95"] <= MARGIN * p95, identity["text"]
    assert identity["ratio"] <= MARGIN * ratio, identity["text"]
    assert identity["registration_ratio"] <= MARGIN * registration_ratio, identity["text"]


@pytest.mark.xfail(strict=True, reason="measured: mean 0.58% / 1.17%, 95th percentile 1.68% / "
                                       "3.02% (seeds 1 / 2): the ears and the neck slide along "
                                       "the surface by 1-4%, the face itself by 0.4-0.8%")
def test_correspondence_meets_the_bars(identity):
    assert identity["mean"] <= MEAN_BAR and identity["p95"] <= P95_BAR, identity["text"]


@pytest.mark.xfail(strict=True, reason="measured: 1.72x / 2.89x the exact registration's error "
                                       "(seeds 1 / 2); the same registrations through "
                                       "fit_registered (no landmarks, so no eyelid rims) give "
                                       "1.79x / 1.79x: the rest of seed 2's is in the eye "
                                       "expressions after the eyelid rims")
def test_transfer_error_is_near_the_exact_registrations(identity):
    assert identity["ratio"] <= RATIO_BAR, identity["text"]
