"""The registration's start from the library's shape space (core/shape_space.py), on faces with a
known answer: the library's own face region made into a new face by the identity modes it
ships, moved by a random similarity. No shared data needed: the modes are the bundled library's.
"""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from exclone_addon.core import shape_space
from exclone_addon.core.cloning import fit_faces
from exclone_addon.core.errors import ExCloneError
from exclone_addon.core.library import load_library
from exclone_addon.core.mesh import PolyMesh
from exclone_addon.core.surface import Surface

FACE = 9409            # the library's face part: vertices 0-9,408


@pytest.fixture(scope="module")
def region():
    """(library, face-region PolyMesh, its triangles, its modes)."""
    library = load_library()
    triangles = library.mesh.triangles()
    triangles = triangles[(triangles < FACE).all(axis=1)]
    mesh = PolyMesh.from_faces(library.mesh.vertices[:FACE], triangles)
    return library, mesh, triangles, library.shape_modes[:, :FACE]


def moved_face(region, weights, seed):
    """The face of the modes' `weights`, turned, scaled and shifted: (target Surface, R, s, t)."""
    _, mesh, triangles, modes = region
    rng = np.random.default_rng(seed)
    rotation = Rotation.from_rotvec(rng.normal(size=3) * 0.15).as_matrix()
    scale, shift = 1.3, rng.normal(size=3) * 5
    face = mesh.vertices + np.tensordot(weights, modes, 1)
    return Surface(face @ rotation.T * scale + shift, triangles), rotation, scale, shift


@pytest.mark.parametrize("seed", [3, 4])
def test_the_fit_finds_the_face_and_its_similarity(region, seed):
    """From the face's own similarity a little off (as a rigid start leaves it), the fit finds
    the weights that made the face and the face itself (seeds 3 / 4: the weights correlate
    0.995 / 0.985, the face 0.063% / 0.116% of the diagonal off; the prior shrinks the
    weights a little)."""
    _, mesh, triangles, modes = region
    weights = np.random.default_rng(seed).standard_normal(len(modes))
    target, rotation, scale, shift = moved_face(region, weights, seed)
    nudge = Rotation.from_rotvec([0.02, -0.03, 0.01]).as_matrix()
    start = mesh.vertices @ (nudge @ rotation).T * (scale * 1.02) + shift + 0.3
    aligned = Surface(start, triangles)
    r, s, t, found, face = shape_space.fit_shape_space(
        aligned, target, modes @ (nudge @ rotation).T * (scale * 1.02), max_distance=0.05)
    error = np.linalg.norm(face - target.vertices, axis=1) / target.diagonal
    assert np.corrcoef(found, weights)[0, 1] > 0.95, (found, weights)
    print(f"seed {seed}: weights correlate {np.corrcoef(found, weights)[0, 1]:.3f}, face {100 * error.mean():.3f}% of the diagonal off")
    assert error.mean() < 0.002, error.mean()
    # the similarity it reports takes the start's neutral to where the face's neutral lies,
    # nearly: a mode can stand in for a little scale or shift (seed 4: 0.25% of the diagonal)
    neutral = mesh.vertices @ rotation.T * scale + shift
    placed = start @ r.T * s + t
    assert np.linalg.norm(placed - neutral, axis=1).mean() / target.diagonal < 0.005
    assert shape_space.plausible(found)


def test_a_face_beyond_the_space_starts_from_the_neutral(region):
    """Weights far beyond a standard normal's (a caricature: every mode at 2.5) are not a face
    of the space: the fit reports it, and the registration starts from the aligned neutral."""
    _, mesh, _, modes = region
    target, *_ = moved_face(region, np.full(len(modes), 2.5), 5)
    target_mesh = PolyMesh.from_faces(target.vertices, target.triangles)
    plain = fit_faces(mesh, target_mesh)
    with_modes = fit_faces(mesh, target_mesh, source_modes=modes)
    assert with_modes.quality["shape_space_start"] is False
    assert with_modes.quality["shape_space_weight_norm"] > 10
    assert np.array_equal(with_modes.registered_source, plain.registered_source)
    assert "shape_space_start" not in plain.quality


def test_modes_of_the_wrong_size_are_refused(region):
    _, mesh, _, modes = region
    target, *_ = moved_face(region, np.zeros(len(modes)), 6)
    with pytest.raises(ExCloneError, match="shape modes"):
        fit_faces(mesh, PolyMesh.from_faces(target.vertices, target.triangles),
                  source_modes=modes[:, :100])
