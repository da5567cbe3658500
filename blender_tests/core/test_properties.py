"""Property-based tests of the cloning core on random meshes and random expression deltas.

Whatever the input, the public entry points either succeed with finite results or raise
ExCloneError with a message a user can read (never another exception); a zero expression
gives exactly zero displacement, a face cloned onto itself gets its own expressions back and
the transfer's solve is linear in the source gradients (docs/method.md §8). Inputs that once
broke a property stay in the suite as @example.

Meshes are built from a small description (kind, size, seed, scale), so a failing example
is one short line. Runs derandomized (the same examples every run) and writes no database.
"""
import re
import tempfile
from collections import namedtuple
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, event, example, given, settings
from hypothesis import strategies as st
from hypothesis.configuration import set_hypothesis_home_dir
from scipy.spatial import Delaunay, QhullError

from exclone_addon.core import data, transfer
from exclone_addon.core.cloning import (CloneSettings, clone_expressions, fit_faces,
                                        fit_registered, transfer_expressions)
from exclone_addon.core.errors import ExCloneError
from exclone_addon.core.landmarks import automatic_landmarks
from exclone_addon.core.library import load_library
from exclone_addon.core.mesh import PolyMesh, checked_triangles, read_obj
from exclone_addon.core.orientation import face_frame
from exclone_addon.core.transfer import Transfer

# hypothesis keeps caches in ./.hypothesis unless told otherwise: tests do not write into the repo
set_hypothesis_home_dir(Path(tempfile.gettempdir()) / "exclone-hypothesis")
SETTINGS = dict(deadline=None, derandomize=True, database=None,
                phases=(Phase.explicit, Phase.generate, Phase.shrink),
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
FAST = CloneSettings(preset="fast")

# ------------------------------------------------------------------------------- random meshes
MeshSpec = namedtuple("MeshSpec", "kind size seed scale")
KINDS = ("cloud", "grid", "face", "coarse_face", "coincident", "collinear", "single",
         "duplicated", "slivers", "soup")


def _grid(k, rng, noise):
    """A k x k height field on [-1, 1]^2 with a bump in the middle (a nose of sorts)."""
    x, y = np.meshgrid(np.linspace(-1, 1, k), np.linspace(-1, 1, k))
    z = 0.5 * np.exp(-4 * (x ** 2 + y ** 2)) + noise * rng.standard_normal(x.shape)
    ids = np.arange(k * k).reshape(k, k)
    quads = np.stack([ids[:-1, :-1], ids[:-1, 1:], ids[1:, 1:], ids[1:, :-1]], axis=-1)
    return np.stack([x, y, z], axis=-1).reshape(-1, 3), quads.reshape(-1, 4)


def _face(rings, segments, offset):
    """A closed, left-right symmetric head-like shell (a UV sphere, longer than wide) with a
    nose; offset=True turns the meridians by half a step so none lies on the symmetry plane."""
    theta = np.linspace(0, np.pi, rings + 2)[1:-1]
    phi = (np.arange(segments) + (0.5 if offset else 0.0)) * 2 * np.pi / segments
    t, p = np.meshgrid(theta, phi, indexing="ij")
    x, y, z = np.sin(t) * np.sin(p), 1.3 * np.cos(t), np.sin(t) * np.cos(p)
    z = z + 0.4 * np.exp(-8 * (x ** 2 + (y - 0.1) ** 2)) * (z > 0)
    vertices = np.vstack([np.stack([x, y, z], axis=-1).reshape(-1, 3), [[0, 1.3, 0], [0, -1.3, 0]]])
    ring = np.arange(rings * segments).reshape(rings, segments)
    nxt = np.roll(ring, -1, axis=1)
    faces = [np.stack([ring[:-1], ring[1:], nxt[1:], nxt[:-1]], axis=-1).reshape(-1, 4)]
    top, bottom = len(vertices) - 2, len(vertices) - 1
    faces.append(np.stack([np.full(segments, top), nxt[0], ring[0], np.full(segments, top)],
                          axis=-1)[:, :3])
    faces.append(np.stack([np.full(segments, bottom), ring[-1], nxt[-1]], axis=-1))
    return vertices, list(faces[0]) + list(faces[1]) + list(faces[2])


def build_mesh(spec):
    """The PolyMesh a MeshSpec describes (deterministic)."""
    rng = np.random.default_rng(spec.seed)
    n = spec.size
    if spec.kind == "cloud":
        vertices = rng.random((n, 3))
        try:
            faces = Delaunay(vertices[:, :2]).simplices
        except QhullError:
            faces = rng.integers(0, n, (n, 3))
    elif spec.kind == "grid":
        vertices, faces = _grid(max(2, n // 3), rng, noise=0.05)
    elif spec.kind in ("face", "coarse_face"):
        coarse = spec.kind == "coarse_face"
        vertices, faces = _face(max(3, n // (6 if coarse else 2)), max(4, n // (4 if coarse else 1)),
                                offset=coarse)
        vertices = vertices + 1e-3 * rng.standard_normal(vertices.shape)
    elif spec.kind == "coincident":
        vertices = np.tile(rng.random(3), (n, 1))
        faces = rng.integers(0, n, (n, 3))
    elif spec.kind == "collinear":
        vertices = np.outer(rng.random(n), rng.standard_normal(3))
        faces = rng.integers(0, n, (n, 3))
    elif spec.kind == "single":
        vertices, faces = rng.standard_normal((3, 3)), [[0, 1, 2]]
    elif spec.kind == "duplicated":
        vertices, faces = _grid(max(2, n // 4), rng, noise=0.0)
        faces = np.vstack([faces, faces, faces[:, ::-1]])
    elif spec.kind == "slivers":            # valid by area, too thin for a gradient
        rows = np.arange(n)[:, None] * 0.1
        vertices = np.stack([np.hstack([rows * 0, rows]), np.hstack([rows * 0 + 1, rows]),
                             np.hstack([rows * 0 + 0.5, rows + 2e-11])], axis=1).reshape(-1, 2)
        vertices = np.column_stack([vertices, rng.random(len(vertices)) * 1e-12])
        faces = np.arange(3 * n).reshape(n, 3)
    else:                                   # a triangle soup: any vertex ids, repeats allowed
        vertices = rng.standard_normal((n, 3))
        faces = rng.integers(0, n, (2 * n, 3))
    return PolyMesh.from_faces(np.asarray(vertices, dtype=np.float64) * spec.scale, faces)


mesh_specs = st.builds(MeshSpec, kind=st.sampled_from(KINDS), size=st.integers(3, 48),
                       seed=st.integers(0, 2 ** 16),
                       scale=st.sampled_from((1.0, 1e-9, 1e-4, 30.0, 1e6, 1e12, 1e-28, 1e28,
                                              1e-150, 1e150)))


def outcome(call, *args, **kwargs):
    """A core entry point's result, or None after an ExCloneError with a message; any other
    exception fails the test."""
    try:
        result = call(*args, **kwargs)
    except ExCloneError as error:
        assert str(error).strip(), "an ExCloneError without a message"
        event(f"{call.__name__}: refused: " + re.sub(r"[-0-9.e]+|/\S+", "#", str(error))[:70])
        return None
    event(f"{call.__name__}: succeeded")
    return result


def random_deltas(n_vertices, count, seed, magnitude):
    """count random expressions of n_vertices, the first one all zero."""
    deltas = magnitude * np.random.default_rng(seed).standard_normal((count, n_vertices, 3))
    deltas[0] = 0.0
    return deltas


# ------------------------------------------------------------------------------- OBJ reading
OBJ_LINES = st.one_of(
    st.text(max_size=30),
    st.builds(lambda xs: "v " + " ".join(xs),
              st.lists(st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr),
                                 st.sampled_from(("x", "", "1e999", "-0"))), max_size=5)),
    st.builds(lambda ids, sep: "f " + " ".join(f"{i}{sep}" for i in ids),
              st.lists(st.integers(-10, 10) | st.integers(-2 ** 70, 2 ** 70), max_size=6),
              st.sampled_from(("", "/", "/1", "//2", "/x"))),
)


@settings(max_examples=80, **SETTINGS)
@given(lines=st.lists(OBJ_LINES, max_size=12), junk=st.binary(max_size=40))
@example(lines=["v "], junk=b"")                              # was read as no vertex at all
@example(lines=["v 1 2", "v 3 4", "v 5 6"], junk=b"")         # was read as two vertices
@example(lines=["v 0 0 0", "f x"], junk=b"")                  # was a ValueError
@example(lines=["v 0 0 0", "f 1 1 36893488147419103232"], junk=b"")   # was an OverflowError
def test_read_obj_reads_a_mesh_or_says_why_not(tmp_path_factory, lines, junk):
    path = tmp_path_factory.mktemp("obj") / "random.obj"
    path.write_bytes("\n".join(lines).encode("utf-8", "surrogatepass") + b"\n" + junk)
    mesh = outcome(read_obj, path)
    if mesh is None:
        return
    vertex_lines = sum(line.startswith("v ") for line in
                       path.read_text("utf-8", errors="replace").splitlines())
    assert mesh.vertices.shape == (vertex_lines, 3)
    if len(mesh.loop_vertices):
        assert 0 <= mesh.loop_vertices.min() and mesh.loop_vertices.max() < len(mesh.vertices)
    checked = outcome(checked_triangles, mesh)
    if checked is not None:
        assert np.isfinite(checked[0]).all() and len(checked[1])


# ------------------------------------------------------------------------------- frame, landmarks
@settings(max_examples=15, **SETTINGS)
@given(spec=mesh_specs)
@example(spec=MeshSpec("grid", 3, 0, 1.0))     # no vertex near the midline: was an empty argmax
@example(spec=MeshSpec("face", 3, 0, 1e150))   # areas overflowed: NaN sampling probabilities
def test_face_frame_and_landmarks_succeed_or_say_why(spec):
    checked = outcome(checked_triangles, build_mesh(spec))
    if checked is None:
        return
    vertices, triangles = checked
    frame = outcome(face_frame, vertices, triangles)
    if frame is None:
        return
    assert np.allclose(frame.rotation.T @ frame.rotation, np.eye(3), atol=1e-9)
    assert np.isfinite(frame.origin).all() and np.isfinite(frame.diagonal)
    found = outcome(automatic_landmarks, vertices, triangles, frame)
    if found is None:
        return
    names, ids = found
    assert len(names) == len(ids) == len(set(names))
    assert np.all((ids >= 0) & (ids < len(vertices)))


# ------------------------------------------------------------------------------- the pipeline
def random_pairs(source, target, seed, count):
    """count random landmark pairs between the meshes' vertices (possibly invalid ones)."""
    rng = np.random.default_rng(seed)
    n_s, n_t = len(source.vertices), len(target.vertices)
    return {"source": rng.choice(n_s, min(count, n_s), replace=False).tolist(),
            "target": rng.choice(n_t, min(count, n_t), replace=False).tolist()}


@settings(max_examples=60, **SETTINGS)
@given(source=mesh_specs, target=mesh_specs, seed=st.integers(0, 2 ** 16),
       pairs=st.integers(3, 12), magnitude=st.sampled_from((0.0, 1e-6, 1e-2, 0.3, 1e6)))
# the zero expression moved every vertex by ~1e-16
@example(source=MeshSpec("cloud", 4, 0, 1.0), target=MeshSpec("cloud", 4, 0, 1.0), seed=0,
         pairs=4, magnitude=0.0)
# a closed target has no border: an empty border query was a reshape ValueError
@example(source=MeshSpec("cloud", 4, 0, 1.0), target=MeshSpec("face", 3, 0, 1.0), seed=0,
         pairs=4, magnitude=0.0)
def test_clone_with_given_landmarks_succeeds_or_says_why(source, target, seed, pairs, magnitude):
    source_mesh, target_mesh = build_mesh(source), build_mesh(target)
    deltas = random_deltas(len(source_mesh.vertices), 2, seed, magnitude * source.scale)
    result = outcome(clone_expressions, source_mesh, deltas, ["zero", "random"], target_mesh,
                     landmarks=random_pairs(source_mesh, target_mesh, seed, pairs), settings=FAST)
    if result is None:
        return
    assert result.deltas.shape == (2, len(target_mesh.vertices), 3)
    assert np.isfinite(result.deltas).all() and np.isfinite(result.registered_source).all()
    assert np.all(result.deltas[0] == 0.0), "a zero expression must not move the target"


# Consistently wound meshes of fairly uniform triangles (the closest-point search only looks at
# the triangles with the nearest centroids, so a random cloud's long slivers may be missed; a
# face duplicated with the opposite winding faces both ways).
WELL_FORMED = ("grid", "face", "coarse_face")


@settings(max_examples=40, **SETTINGS)
@given(spec=mesh_specs, seed=st.integers(0, 2 ** 16))
@example(spec=MeshSpec("slivers", 3, 0, 1.0), seed=0)   # no usable gradient: was a RuntimeError
def test_a_face_cloned_onto_itself_gets_its_own_expressions(spec, seed):
    """Through its own registration (every vertex where it is), a mesh's expressions come back
    unchanged; on any mesh the transfer succeeds or says why."""
    mesh = build_mesh(spec)
    fit = outcome(fit_registered, mesh, mesh, mesh.vertices)
    if fit is None:
        return
    deltas = random_deltas(len(mesh.vertices), 2, seed, 0.01 * spec.scale)
    result = outcome(transfer_expressions, fit, deltas, ["zero", "random"])
    if result is None:
        return
    assert np.isfinite(result.deltas).all() and np.all(result.deltas[0] == 0.0)
    if spec.kind in WELL_FORMED:
        used = np.unique(fit.target_region.triangles)
        error = np.abs(result.deltas[1, used] - deltas[1, used]).max()
        assert error <= 1e-6 * np.abs(deltas[1]).max()


face_specs = st.builds(MeshSpec, kind=st.sampled_from(("face", "coarse_face", "grid")),
                       size=st.integers(8, 48), seed=st.integers(0, 2 ** 16),
                       scale=st.sampled_from((1.0, 1e-4, 1e6)))


@settings(max_examples=8, **SETTINGS)
@given(source=face_specs, target=face_specs, seed=st.integers(0, 2 ** 16))
def test_fit_with_automatic_landmarks_succeeds_or_says_why(source, target, seed):
    source_mesh, target_mesh = build_mesh(source), build_mesh(target)
    fit = outcome(fit_faces, source_mesh, target_mesh, settings=FAST)
    if fit is None:
        return
    assert np.isfinite(fit.registered_source).all()
    deltas = random_deltas(len(source_mesh.vertices), 2, seed, 0.01 * source.scale)
    result = outcome(transfer_expressions, fit, deltas, ["zero", "random"])
    if result is not None:
        assert np.isfinite(result.deltas).all() and np.all(result.deltas[0] == 0.0)


# ------------------------------------------------------------------------------- transfer
@pytest.fixture(scope="module")
def known_fit():
    """The bundled library fitted onto the demo head (a pair known to clone well), once."""
    library = load_library()
    fit = fit_faces(library.mesh, data.demo_head(), source_landmarks=library.automatic_landmarks)
    return fit, library.deltas


def _transfer(fit, deltas):
    return transfer_expressions(fit, deltas, [f"e{k}" for k in range(len(deltas))]).deltas


@settings(max_examples=8, **SETTINGS)
@given(seed=st.integers(0, 2 ** 16), magnitude=st.sampled_from((1e-6, 0.01, 1.0)),
       mix=st.booleans())
def test_zero_stays_zero_and_expressions_do_not_mix(known_fit, seed, magnitude, mix):
    """A zero expression moves nothing, and the solve gives an expression the same clone
    whatever others are transferred with it (one multi-column solve). The transfer's stretch
    bound is off for the second part: it caps the goals of all the expressions of a call in one
    region where one of them passes it (so that jawOpen and mouthClose still undo each other),
    which makes them depend on each other there (docs/method.md §8, "Stretch bounded")."""
    fit, library_deltas = known_fit
    rng = np.random.default_rng(seed)
    if mix:     # real expressions, mixed
        d1, d2 = np.tensordot(rng.random((2, len(library_deltas))), library_deltas, axes=1)
    else:       # arbitrary motion of every vertex
        d1, d2 = magnitude * rng.standard_normal((2,) + library_deltas.shape[1:])
    zero, t1, t2 = _transfer(fit, np.stack([np.zeros_like(d1), d1, d2]))
    assert np.all(zero == 0.0)
    assert np.isfinite(t1).all() and np.isfinite(t2).all()
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(transfer, "STRETCH_BOUND", np.inf)
        together = _transfer(fit, np.stack([d1, d2]))[1]
        alone = _transfer(fit, d2[None])[0]
    assert np.abs(alone - together).max() <= 1e-12 * np.abs(together).max()


@pytest.fixture(scope="module")
def known_transfer(known_fit):
    """The fitted pair's transfer system, and the target vertices that carry an anchor."""
    fit, _ = known_fit
    system = Transfer(fit.target_region.vertices, fit.target_region.triangles, fit.weights,
                      fit.formulation)
    return system, np.flatnonzero(fit.vertex_map.valid)


@settings(max_examples=10, **SETTINGS)
@given(seed=st.integers(0, 2 ** 16), a=st.floats(-1e3, 1e3, allow_nan=False))
def test_transfer_is_linear_in_the_source_gradients(known_transfer, seed, a):
    """The solve is linear in what the source asks for: each triangle's departure from the
    identity gradient and the anchors' displacements. (The clone as a whole is not linear in
    the source's vertex motion: Sumner's 4th vertex of a deformed source triangle is not.)"""
    system, anchors = known_transfer
    rng = np.random.default_rng(seed)
    identity = np.eye(3)
    n_triangles = len(system.row_weight)
    g1, g2 = 0.1 * rng.standard_normal((2, 1, n_triangles, 3, 3))
    m1, m2 = 0.1 * rng.standard_normal((2, 1, len(anchors), 3))
    combined = system(identity + a * g1 + g2, a * m1 + m2, anchors)
    expected = a * system(identity + g1, m1, anchors) + system(identity + g2, m2, anchors)
    assert np.isfinite(combined).all()
    assert np.abs(combined - expected).max() <= 1e-9 * np.abs(expected).max()


@settings(max_examples=12, **SETTINGS)
@given(shape=st.sampled_from(("vertices", "axes", "names", "nan", "inf", "empty")),
       seed=st.integers(0, 2 ** 16))
@example(shape="empty", seed=0)        # no expressions at all: was a reshape ValueError
def test_transfer_refuses_bad_deltas_with_a_message(known_fit, shape, seed):
    fit, library_deltas = known_fit
    deltas = np.random.default_rng(seed).standard_normal((2,) + library_deltas.shape[1:])
    names = ["a", "b"]
    if shape == "vertices":
        deltas = deltas[:, :-1]
    elif shape == "axes":
        deltas = deltas[..., :2]
    elif shape == "names":
        names = ["a"]
    elif shape in ("nan", "inf"):
        deltas[1, seed % deltas.shape[1], seed % 3] = np.nan if shape == "nan" else np.inf
    else:
        deltas, names = deltas[:0], []
    result = outcome(transfer_expressions, fit, deltas, names)
    if shape == "empty":        # nothing to clone: refused, or nothing cloned
        assert result is None or result.deltas.shape == (0, len(fit.target.vertices), 3)
    else:
        assert result is None, f"deltas with bad {shape} were accepted"


@settings(max_examples=20, **SETTINGS)
@given(expressions=st.integers(1, 9), vectors=st.integers(0, 5), seed=st.integers(0, 2 ** 16))
@example(expressions=3, vectors=0, seed=0)   # no vectors: was a reshape ValueError
def test_the_solves_column_layout_round_trips(expressions, vectors, seed):
    """transfer.as_columns and as_rows are inverses for any count of expressions and vectors,
    none included (the stretch bound's rounds may reach only triangles without an image)."""
    values = np.random.default_rng(seed).standard_normal((expressions, vectors, 3))
    columns = transfer.as_columns(values)
    assert columns.shape == (vectors, 3 * expressions)
    assert columns[:, expressions:2 * expressions].T.tolist() == values[..., 1].tolist()
    assert np.array_equal(transfer.as_rows(columns), values)
