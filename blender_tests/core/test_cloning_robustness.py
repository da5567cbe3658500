"""The pipeline on awkward but legal meshes: degenerate triangles, duplicate vertices, an
unreferenced vertex, a separate part the source does not cover, quads and n-gons."""

import numpy as np
import pytest

from exclone_addon.core import data
from exclone_addon.core.cloning import clone_expressions
from exclone_addon.core.errors import ExCloneError
from exclone_addon.core.library import load_library
from exclone_addon.core.mesh import PolyMesh, read_obj

DEMO_HEAD = data.DEMO_HEAD_FILE
NAMES = ("jawOpen", "eyeBlink_L")


@pytest.fixture(scope="module")
def source():
    lib = load_library().subset(list(NAMES))
    return lib.mesh, lib.deltas


def awkward_head():
    """The demo head (quads) plus: a zero-area triangle, a duplicate of vertex 0 used by a
    degenerate triangle only, an unreferenced vertex, and a detached pentagon far behind."""
    head = read_obj(DEMO_HEAD)
    v = head.vertices
    n = len(v)
    extra = np.array([v[0],                                    # n: duplicate of vertex 0
                      [9.0, 9.0, 9.0]])                        # n+1: unreferenced
    ring = v.mean(axis=0) + [0.0, 0.0, -3.0] + 0.1 * np.array(
        [[np.cos(a), np.sin(a), 0.0] for a in np.linspace(0, 2 * np.pi, 5, endpoint=False)])
    faces = head.faces() + [np.array([0, 1, 1]),               # two corners the same
                            np.array([0, n, 1]),               # duplicate vertex: zero area
                            np.arange(n + 2, n + 7)]           # detached pentagon (n-gon)
    return PolyMesh.from_faces(np.vstack([v, extra, ring]), faces), n


def test_awkward_target_gives_finite_keys_and_leaves_the_rest_alone(source):
    mesh, deltas = source
    target, n = awkward_head()
    result = clone_expressions(mesh, deltas, list(NAMES), target)
    assert np.isfinite(result.deltas).all()
    assert np.all(result.deltas[:, n + 1] == 0.0), "an unreferenced vertex must not move"
    assert np.abs(result.deltas[:, n + 2:]).max() < 1e-9, "a part the source does not cover stays"
    # the duplicate of vertex 0 sits on degenerate triangles only: it follows its original
    assert np.allclose(result.deltas[:, n], result.deltas[:, 0])
    # and the head itself still opens its mouth
    assert np.linalg.norm(result.deltas[0, :n], axis=1).max() > 0.1


def test_source_with_degenerate_triangles_and_unreferenced_vertices(source):
    mesh, deltas = source
    v = np.vstack([mesh.vertices, mesh.vertices[:1], [[50.0, 50.0, 50.0]]])
    n = len(mesh.vertices)
    faces = mesh.faces() + [np.array([0, 1, 1]), np.array([0, n, 1])]
    padded = np.concatenate([deltas, np.zeros((len(deltas), 2, 3))], axis=1)
    padded[:, n + 1] = 1e3          # an unreferenced source vertex's delta must not matter
    result = clone_expressions(PolyMesh.from_faces(v, faces), padded, list(NAMES),
                               read_obj(DEMO_HEAD))
    assert np.isfinite(result.deltas).all()
    assert np.abs(result.deltas).max() < 1.0   # demo head is ~2.6 units wide: no blow-up


def test_mismatched_deltas_are_a_clear_error(source):
    mesh, deltas = source
    with pytest.raises(ExCloneError, match="expected"):
        clone_expressions(mesh, deltas[:, :100], list(NAMES), read_obj(DEMO_HEAD))
    with pytest.raises(ExCloneError, match="names"):
        clone_expressions(mesh, deltas, ["only_one"], read_obj(DEMO_HEAD))


def test_one_fit_serves_several_transfers_and_shipped_landmarks_match_found_ones():
    """fit_faces + transfer_expressions give what clone_expressions gives, the second transfer
    reuses the factorisation, and the library's shipped landmarks are the ones it would find."""
    from exclone_addon.core.cloning import fit_faces, transfer_expressions
    from exclone_addon.core.landmarks import automatic_landmarks
    lib = load_library()
    names, ids = lib.automatic_landmarks
    found_names, found_ids = automatic_landmarks(lib.mesh.vertices, lib.mesh.triangles())
    assert list(found_names) == list(names) and np.array_equal(found_ids, ids)

    subset = lib.subset(list(NAMES))
    target = read_obj(DEMO_HEAD)
    fit = fit_faces(lib.mesh, target, source_landmarks=lib.automatic_landmarks)
    both = transfer_expressions(fit, subset.deltas, list(NAMES))
    factorised = fit._transfer
    one = transfer_expressions(fit, subset.deltas[1:], list(NAMES[1:]))
    assert fit._transfer is factorised
    np.testing.assert_allclose(one.deltas[0], both.deltas[1], atol=1e-12)
    whole = clone_expressions(lib.mesh, subset.deltas, list(NAMES), target,
                              source_landmarks=lib.automatic_landmarks)
    np.testing.assert_allclose(whole.deltas, both.deltas, atol=1e-9)
    assert whole.landmark_names == fit.landmark_names
    with pytest.raises(ExCloneError, match="eyeBlink_L.*units or scales"):
        transfer_expressions(fit, subset.deltas * [[[1.0]], [[1e30]]], list(NAMES))
    with pytest.raises(ExCloneError, match="landmarks do not fit"):
        fit_faces(lib.mesh, target, source_landmarks=(["nose_tip"], np.array([len(lib.mesh.vertices)])))


def test_registration_made_elsewhere_must_fit_the_source(source):
    from exclone_addon.core.cloning import fit_registered
    mesh, _ = source
    target = read_obj(DEMO_HEAD)
    with pytest.raises(ExCloneError, match="registered source has shape"):
        fit_registered(mesh, target, mesh.vertices[:-1])
    broken = np.array(mesh.vertices, dtype=np.float64)
    broken[3] = np.nan
    with pytest.raises(ExCloneError, match="invalid values"):
        fit_registered(mesh, target, broken)


def test_absurd_expressions_are_refused_before_the_long_work(source):
    """Deltas made at another scale than the neutral (1e30 times, or one vertex moving further
    than the whole face measures) are named in one clear error, before any fitting starts."""
    mesh, deltas = source
    calls = []

    def progress(fraction, message):
        calls.append(message)

    huge = deltas.copy()
    huge[1] *= 1e30
    with pytest.raises(ExCloneError, match=r"expression\(s\) eyeBlink_L move .*units or scales"):
        clone_expressions(mesh, huge, list(NAMES), read_obj(DEMO_HEAD), progress=progress)
    one_far = deltas.copy()
    size = np.linalg.norm(np.ptp(mesh.vertices[np.unique(mesh.triangles())], axis=0))
    one_far[0, 123] = [0.0, 1.5 * size, 0.0]
    with pytest.raises(ExCloneError, match=r"jawOpen move .*more than the whole source mesh"):
        clone_expressions(mesh, one_far, list(NAMES), read_obj(DEMO_HEAD), progress=progress)
    assert calls == [], "the check must come before the fit"


@pytest.mark.parametrize("settings, valid", [
    (dict(preset="slow"), "fast, balanced, precise"),
    (dict(formulation="sumner"), "reduced, augmented"),
    (dict(correspondence="nearest"), "vertex, triangle"),
    (dict(max_distance=-1.0), "positive number"),
    (dict(landmark_weight=float("nan")), "positive number"),
])
def test_unknown_settings_say_what_is_valid(source, settings, valid):
    from exclone_addon.core.cloning import CloneSettings
    mesh, deltas = source
    with pytest.raises(ExCloneError, match=valid):
        clone_expressions(mesh, deltas, list(NAMES), read_obj(DEMO_HEAD),
                          settings=CloneSettings(**settings))


def test_degenerate_geometry_is_a_clear_error_not_a_nan():
    """Finite but degenerate input to the steps themselves: points on a line to align, a
    source region with no triangles, an unknown preset or formulation."""
    from exclone_addon.core import deformation
    from exclone_addon.core.registration import Schedule, register, similarity_transform
    from exclone_addon.core.surface import Surface
    points = np.ones((5, 3))
    spread = np.random.default_rng(0).normal(size=(5, 3))
    line = np.linspace(0, 1, 5)[:, None] * [1.0, 2.0, 3.0] + 7.0
    for a, b in ((points, spread), (spread, points), (np.zeros((5, 3)), spread), (line, spread),
                 (spread, line)):
        with pytest.raises(ExCloneError, match="on one line or at one point"):
            similarity_transform(a, b)
    corners = np.array([[1.0, 1, 0], [-1, 1, 0], [-1, -1, 0], [1, -1, 0]])
    with pytest.raises(ExCloneError, match="fix no rotation"):     # a square paired crosswise
        similarity_transform(corners, corners[[2, 1, 3, 0]])
    square = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    target = Surface(square, [[0, 1, 2], [0, 2, 3]])
    with pytest.raises(ExCloneError, match="lie on no face of the source"):
        register(Surface(square, np.zeros((0, 3))), target, [0], square[:1])
    from exclone_addon.core.proximity import SegmentSet
    assert SegmentSet(square, [[0, 1]]).closest(np.zeros((0, 3)))[0].shape == (0, 3)
    with pytest.raises(ExCloneError, match="fast, balanced, precise"):
        Schedule.preset("quick")
    with pytest.raises(ExCloneError, match="reduced, augmented"):
        deformation.gradient_operator(square, target.triangles, "sumner")
