"""core.rims' correction on the transfer's own factorisation gives the correction the module
docstring defines: the solution of (A + S^T P S) c = S^T P r on the free unknowns (A the
transfer's normal matrix), solved directly here, each floating part then translated to no mean
motion at its anchors, for free-floating parts and held ones, in both formulations."""
import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve

from exclone_addon.core import data, deformation, rims
from exclone_addon.core.mesh import diagonal
from exclone_addon.core.transfer import Transfer


@pytest.fixture(scope="module")
def head():
    mesh = data.demo_head()
    return mesh.vertices, mesh.triangles()


def direct_correction(transfer, ids, pull, offsets, anchors):
    """(E, n, 3) by one sparse solve of the whole system with the pull on its diagonal, each part
    without a fixed vertex moved to no mean motion at its anchors."""
    normal = transfer.grad.T @ sp.diags(np.repeat(transfer.row_weight, 3)) @ transfer.grad
    pin = np.zeros(normal.shape[0])
    pin[ids] = pull
    free = transfer.free
    system = sp.csc_matrix((normal + sp.diags(pin))[free][:, free])
    out = np.zeros((len(offsets), transfer.n, 3))
    for e, offset in enumerate(offsets):
        rhs = np.zeros((normal.shape[0], 3))
        rhs[ids] = pull[:, None] * offset
        solution = np.zeros_like(rhs)
        solution[free] = spsolve(system, rhs[free])
        out[e] = solution[: transfer.n]
    parts = transfer.parts[: transfer.n]
    for part in np.setdiff1d(np.unique(parts), parts[transfer.fixed]):
        mine = parts == part
        out[:, mine] -= out[:, anchors[mine[anchors]]].mean(axis=1, keepdims=True)
    return out


@pytest.mark.parametrize("formulation", deformation.FORMULATIONS)
@pytest.mark.parametrize("held", [False, True])
def test_correction_is_the_direct_solve(head, formulation, held):
    vertices, triangles = head
    # the lowest vertices held (a neck cut), or none: the head's part then floats
    fixed = np.argsort(vertices[:, 1])[:200] if held else ()
    transfer = Transfer(vertices, triangles, np.ones(len(triangles)), formulation, fixed)
    rng = np.random.default_rng(7)
    ids = rng.choice(np.flatnonzero(transfer.free[: len(vertices)]), 40, replace=False)
    pull = rng.uniform(50.0, 200.0, len(ids))      # each rim vertex its own weight
    offsets = rng.normal(size=(5, len(ids), 3)) * 0.01 * diagonal(vertices)
    anchors = np.sort(rng.choice(len(vertices), len(vertices) // 2, replace=False))
    found = rims._Correction(transfer, ids, pull, anchors)(offsets)
    wanted = direct_correction(transfer, ids, pull, offsets, anchors)
    assert np.abs(wanted).max() > 1e-3 * diagonal(vertices)       # the rims do move
    assert np.abs(found - wanted).max() < 1e-6 * diagonal(vertices)
    if held:
        assert not found[:, transfer.fixed].any()
