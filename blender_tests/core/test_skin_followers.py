"""Lashes and eye shells closing with the lids (core/followers.py, docs/method.md §9): an ICT-style
head that is not the library's base mesh (the library's own mesh numbered differently, as a
.glb/.fbx export of an ICT head is, or an ICT identity so numbered) goes through the registration,
and its eyelashes and eye shells (the occlusion / lacrimal / "eye blend" shells over the front of
the eyeball) follow the solved skin as skin pieces. The truth is the library's own motion of
those parts in its eye closure."""
import numpy as np
import pytest

from blender_tests.helpers.paths import SHARED_DATA
from exclone_addon.core import character
from exclone_addon.core.cloning import clone_expressions
from exclone_addon.core.library import load_library
from exclone_addon.core.mesh import PolyMesh

ICT_IDENTITIES = SHARED_DATA / "ict-facekit" / "identities.npz"
# error max as a fraction of the part's largest motion, edges' largest stretch. Before (each
# point hanging from its one nearest root): shells 0.67 / 8.6x on the library's mesh, 0.58 /
# 9.1x on identity 4, lashes 0.73 / 3.4x and 0.85 / 6.4x: shards (the library's own stretch
# 1.9-2.7x on the shells, 1.5-1.6x on the lashes); after: shells 0.51 / 2.5x and 0.39 / 3.5x,
# lashes 0.46 / 1.4x and 0.51 / 1.8x
BARS = {"eye_blend_occlusion": (0.6, 5.0), "eyelashes": (0.65, 2.5)}


@pytest.fixture(scope="module")
def library():
    return load_library()


def renumbered_blink(library, vertices):
    """eyeBlink_L cloned onto `vertices` (the library's topology) numbered differently, through
    character.find and the registration; (E=1, n, 3) back in the library's numbering."""
    order = np.random.default_rng(0).permutation(len(vertices))
    inverse = np.argsort(order)
    mesh = PolyMesh(vertices[order], library.mesh.loop_totals,
                    inverse[library.mesh.loop_vertices])
    blink = library.subset(["eyeBlink_L"])
    found = character.find([character.Part("head", mesh)])
    result = clone_expressions(blink.mesh, blink.deltas, blink.names, found.head.mesh,
                               source_landmarks=blink.automatic_landmarks,
                               face_guide=found.guide, fixed_vertices=found.head.fixed)
    return found.head.spread(result.deltas)[:, inverse], blink.deltas


def identity(library, seed):
    if not ICT_IDENTITIES.exists():
        pytest.skip(f"needs the shared data's ICT-FaceKit identities ({ICT_IDENTITIES})")
    with np.load(ICT_IDENTITIES) as modes:
        modes = modes["deltas"].astype(np.float64)
    weights = np.random.default_rng(seed).standard_normal(len(modes))
    return library.mesh.vertices + np.tensordot(weights, modes, 1)


@pytest.mark.parametrize("seed", [None, 4], ids=["library mesh", "identity 4"])
def test_lashes_and_eye_shells_close_with_the_lids(library, seed):
    vertices = library.mesh.vertices if seed is None else identity(library, seed)
    ours, truth = renumbered_blink(library, vertices)
    triangles = library.mesh.triangles()
    for part, (error_bar, stretch_bar) in BARS.items():
        a, b = library.parts[part]
        error = np.linalg.norm(ours[0, a:b] - truth[0, a:b], axis=1)
        peak = np.linalg.norm(truth[0, a:b], axis=1).max()
        # the closing eye's edges (x > 0: the character's left)
        inside = triangles[((triangles >= a) & (triangles < b)).all(axis=1)]
        edges = np.concatenate([inside[:, [0, 1]], inside[:, [1, 2]], inside[:, [2, 0]]])
        edges = edges[vertices[edges[:, 0], 0] > 0]
        rest = np.linalg.norm(np.subtract(*vertices[edges.T]), axis=1)
        stretch = {name: np.linalg.norm(np.subtract(*(vertices + d[0])[edges.T]), axis=1) / rest
                   for name, d in (("ours", ours), ("library", truth))}
        print(f"{part}: error mean {error.mean() / peak:.2f} max {error.max() / peak:.2f} of its "
              f"largest motion ({peak:.2f} cm); edges stretched up to {stretch['ours'].max():.2f}x "
              f"(the library's {stretch['library'].max():.2f}x)")
        assert error.max() < error_bar * peak, part
        assert stretch["ours"].max() < stretch_bar, part
