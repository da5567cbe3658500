"""The face's own frame from its geometry (docs/method.md §3): left-right symmetry plane, forward
(nose), up.

Canonical frame (the method's): +X the character's left, +Y up, +Z forward (nose direction).
Supported inputs: a face in Blender's front view (-Y forward, +Z up), a Y-up import (+Z forward,
+Y up), or either rotated by up to 30 degrees about any axis.

1. Symmetry plane: mirror a surface sample through candidate planes and keep the one whose mirror
   image lands back on the surface, then refine it from mirrored point pairs.
2. Forward: within the symmetry plane, the direction whose extreme point protrudes most from its
   surroundings: the nose tip beats the chin, the top or the back of the head.
3. Up: perpendicular to forward in the plane; its sign from the nose's own asymmetry (the
   profile drops steeply below the tip, gently along the dorsum above it), cross-checked with the
   supported input conventions (+Y or +Z roughly up).
A frame that fails a check raises ExCloneError asking for manual landmarks.
"""
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from .errors import ExCloneError
from .mesh import boundary_vertices, diagonal, triangle_areas, triangle_normals
from .proximity import TriangleSurface

_MANUAL = "place the landmarks by hand (or give --landmarks)"


@dataclass
class FaceFrame:
    rotation: np.ndarray   # (3, 3): columns are the face's +X (left), +Y (up), +Z (forward) in mesh coords
    origin: np.ndarray     # (3,): a point on the symmetry plane
    diagonal: float        # bounding-box diagonal of the mesh
    symmetry_error: float  # mean mirror mismatch / diagonal

    def to_canonical(self, points):
        return (np.asarray(points) - self.origin) @ self.rotation



def surface_samples(vertices, triangles, count=6000, seed=0):
    """Area-uniform random points on the surface and their triangles' unit normals.

    Deterministic for a seed and equivariant: a rotated or scaled copy of a mesh gets the same
    points on its surface.
    """
    area = triangle_areas(vertices, triangles)
    total = area.sum()
    if total <= 0:
        raise ExCloneError("mesh has no surface area")
    rng = np.random.default_rng(seed)
    tri = rng.choice(len(triangles), size=count, p=area / total)
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    points = np.einsum("ij,ijk->ik", w, vertices[triangles[tri]])
    return points, triangle_normals(vertices, triangles[tri])


def _fibonacci_directions(count):
    i = np.arange(count) + 0.5
    z = 1 - 2 * i / count
    phi = np.pi * (1 + 5 ** 0.5) * i
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _mirror(points, normal, offset):
    return points - 2.0 * (points @ normal - offset)[:, None] * normal


def mirror_errors(tree, centre, normals, points):
    """(d,) per unit plane normal (normals (d, 3), planes through `centre`): the mean distance of
    the points' mirror images to the points the KD-tree `tree` holds."""
    heights = (points - centre) @ normals.T                                  # (p, d)
    images = points[None] - 2.0 * heights.T[:, :, None] * normals[:, None]  # (d, p, 3)
    return tree.query(images.reshape(-1, 3), workers=-1)[0].reshape(len(normals), -1).mean(1)


def symmetry_plane(samples, diagonal, surface, candidates=600):
    """Plane (unit normal, offset) with normal . x = offset that best mirrors the surface onto itself.

    A coarse search over candidate normals through the centroid, then a mirror ICP from the best
    few: the mirrored samples are aligned rigidly to their closest surface points, and the plane
    is read off the resulting reflection (its -1 eigenvector and its offset).
    """
    tree = cKDTree(samples)
    probe = samples[:: max(1, len(samples) // 400)]
    centre = samples.mean(axis=0)
    dirs = _fibonacci_directions(2 * candidates)
    dirs = dirs[dirs[:, 2] >= 0]                           # a plane normal and its negative are one plane

    # every candidate with a quarter of the probes, then the 50 best with all of them (the best
    # three are the same as with all probes for all: checked on the shared and bundled heads,
    # masks and 3 rotations of each)
    dirs = dirs[np.argsort(mirror_errors(tree, centre, dirs, probe[::4]))[:50]]
    starts = dirs[np.argsort(mirror_errors(tree, centre, dirs, probe))[:3]]
    points = samples[:: max(1, len(samples) // 1500)]
    # the starts are independent: two at a time (numpy and the KD-tree release the GIL); after
    # a few steps the best of them goes on alone (ICP creeps: the order is set early)
    with ThreadPoolExecutor(max_workers=2) as pool:
        planes = list(pool.map(lambda d: _mirror_icp(points, surface, d, d @ centre,
                                                     steps=TRIAL_STEPS), starts))
    normal, offset, error = min(planes, key=lambda plane: plane[2])
    normal, offset, error = _mirror_icp(points, surface, normal, offset, MIRROR_STEPS - TRIAL_STEPS)
    return normal, offset, error / diagonal


# Mirror ICP steps from each of the three starts, and in all (the best start goes on alone).
TRIAL_STEPS = 4
MIRROR_STEPS = 15


def _mirror_icp(points, surface, normal, offset, steps):
    """Refine a symmetry plane; returns (normal, offset, mean mirror mismatch of the points)."""
    for _ in range(steps):
        image = _mirror(points, normal, offset)
        closest, _, dist, _ = surface.closest(image)
        keep = dist <= np.quantile(dist, 0.8)                # ignore the asymmetric fraction
        rotation, _ = Rotation.align_vectors(closest[keep] - closest[keep].mean(axis=0),
                                             image[keep] - image[keep].mean(axis=0))
        r = rotation.as_matrix()
        shift = closest[keep].mean(axis=0) - r @ image[keep].mean(axis=0)
        # composed map x -> r (H x + 2 offset normal) + shift is (nearly) a reflection
        linear = r @ (np.eye(3) - 2.0 * np.outer(normal, normal))
        values, vectors = np.linalg.eig(linear)
        new = np.real(vectors[:, np.argmin(np.real(values))])
        new = new if new @ normal > 0 else -new
        new /= np.linalg.norm(new)
        new_offset = float((r @ (2.0 * offset * normal) + shift) @ new) / 2.0
        moved = np.degrees(np.arccos(np.clip(new @ normal, -1, 1)))
        normal, offset = new, new_offset
        if moved < 0.01:
            break
    return normal, offset, surface.closest(_mirror(points, normal, offset))[2].mean()


def _protrusion(samples, tree, direction, candidates, radius):
    """How far the extreme candidate in `direction` stands out of its neighbourhood."""
    height = samples @ direction
    tip = candidates[np.argmax(height[candidates])]
    around = tree.query_ball_point(samples[tip], radius)
    return height[tip] - height[around].mean(), tip


def face_frame(vertices, triangles, search=None):
    """The FaceFrame of a face or head mesh (see module docstring). Raises ExCloneError if unsure.

    search: the surface's proximity.TriangleSurface if already built (a surface.Surface's).
    """
    size = diagonal(vertices, np.unique(triangles))
    samples, normals = surface_samples(vertices, triangles)
    search = search if search is not None else TriangleSurface(vertices, triangles)
    normal, offset, sym_error = symmetry_plane(samples, size, search)
    if sym_error > 0.02:
        raise ExCloneError(
            f"could not find the face's left-right symmetry (mirror mismatch {100 * sym_error:.1f}% "
            f"of its size); {_MANUAL}")
    forward = _forward(samples, normals, vertices[boundary_vertices(triangles)], normal, offset,
                       size)
    up = _up(forward, normal)
    left = np.cross(up, forward)
    rotation = np.stack([left, up, forward], axis=1)
    origin = samples.mean(axis=0)
    origin = origin - (origin @ normal - offset) * normal  # on the symmetry plane
    return FaceFrame(rotation, origin, size, float(sym_error))


def _forward(samples, normals, border, normal, offset, size):
    """The nose's direction: the most protruding extreme direction within the symmetry plane
    (normal . x = offset). Tips next to an open border (points `border`: a mask's edge, a neck
    cut) do not count: they stick out of nothing."""
    candidates = np.abs(samples @ normal - offset) < 0.03 * size
    if len(border):
        candidates &= cKDTree(border).query(samples)[0] > 0.05 * size
    candidates = np.flatnonzero(candidates)
    if len(candidates) < 10:
        raise ExCloneError(f"the face's profile is too small to find its nose; {_MANUAL}")
    basis = np.linalg.svd(np.eye(3) - np.outer(normal, normal))[0][:, :2]
    angles = np.radians(np.arange(0, 360, 1.0))
    directions = np.cos(angles)[:, None] * basis[:, 0] + np.sin(angles)[:, None] * basis[:, 1]
    tree = cKDTree(samples)
    radius = 0.08 * size
    scores = np.array([_protrusion(samples, tree, d, candidates, radius)[0] for d in directions])
    smooth = np.convolve(np.r_[scores[-7:], scores, scores[:7]], np.ones(15) / 15, mode="valid")
    forward = directions[np.argmax(smooth)]
    # Refine continuously (a grid's argmax would differ by a degree or two between rotated
    # copies): forward is the mean outward normal of the face around the nose tip.
    _, tip = _protrusion(samples, tree, forward, candidates, radius)
    around = tree.query_ball_point(samples[tip], 0.25 * size)
    outward = normals[around] * np.sign(normals[around] @ forward)[:, None]
    mean_normal = outward.sum(axis=0)
    mean_normal -= (mean_normal @ normal) * normal
    if np.linalg.norm(mean_normal) > 0:
        forward = mean_normal / np.linalg.norm(mean_normal)
    return forward


def _up(forward, normal):
    """Up: perpendicular to forward within the symmetry plane, signed like the supported
    conventions' up (+Y for a Y-up import, +Z in Blender's front view): whichever is further
    from forward."""
    up = np.cross(forward, normal)
    up /= np.linalg.norm(up)
    world_up = min(np.eye(3)[1:], key=lambda axis: abs(axis @ forward))
    if world_up @ up < 0:
        up = -up
    if world_up @ up < np.cos(np.radians(50)):
        raise ExCloneError(
            "the face's up direction is neither +Y nor +Z (within 50 degrees) by its geometry; "
            + _MANUAL)
    return up


def vertex_symmetry_plane(vertices, triangles, max_steps=100):
    """(unit normal, offset) of the left-right symmetry plane n . x = offset, exact enough that a
    mirror-symmetric mesh maps each vertex onto its twin (for mirrored landmark editing): the face
    frame's plane (good to about a degree), then refit to the midpoints of the better half of the
    reflected-vertex / nearest-vertex pairs until the pairs stop changing."""
    frame = face_frame(vertices, triangles)
    normal, offset = frame.rotation[:, 0], float(frame.rotation[:, 0] @ frame.origin)
    tree = cKDTree(vertices)
    previous = None
    for _ in range(max_steps):
        distance, twin = tree.query(_mirror(vertices, normal, offset))
        if previous is not None and np.array_equal(twin, previous):
            break
        previous = twin
        keep = distance <= np.median(distance)
        middle = (vertices[keep] + vertices[twin[keep]]) / 2     # true twins' midpoints lie on it
        centre = middle.mean(axis=0)
        fitted = np.linalg.svd(middle - centre, full_matrices=False)[2][-1]
        normal = fitted if fitted @ normal >= 0 else -fitted
        offset = float(normal @ centre)
    return normal, offset
