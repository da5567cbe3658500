"""Orthographic renders of a mesh for the face models, with a triangle-id buffer (docs/method.md §4).

Pure numpy/OpenCV (no bpy): face finding runs in core tests and off Blender's main thread.
A z-buffer rasteriser, vectorised over (triangle, pixel) pairs: every pixel centre inside a
triangle's projection is a candidate, the one nearest the camera wins. Shading is smooth
(interpolated vertex normals), two-sided (a mesh with flipped windings still renders) and lit from
the camera (a headlight), in a skin-like grey that the face models read as a face. Every pixel
keeps the id of the triangle it shows, so a point found in the image goes back onto the surface
exactly (`Render.surface_points`).

Pixel coordinates are OpenCV's: the centre of pixel (column i, row j) is (i, j); image x grows
along the camera's right, image y along its down.
"""
from dataclasses import dataclass

import numpy as np

from .mesh import vertex_normals

# Skin-like grey (BGR) under a headlight. Measured on close views of four shared heads, the
# detector's score moves by at most 0.02 between this, mid-grey and white, or with the light from
# above (docs/method.md §4): the shape reads as a face, the colour hardly matters.
SKIN_BGR = np.array([150.0, 170.0, 205.0])
AMBIENT = 0.25
# Candidate (triangle, pixel) pairs per batch: bounds the rasteriser's working memory (find_face
# peaks ~90 MB above its input on the 67k-vertex head).
PAIRS_PER_BATCH = 500_000


@dataclass(frozen=True)
class Camera:
    """An orthographic camera: `axes` rows are its right, up and backward (towards the viewer)
    directions in world space; `centre` (world) is seen at the image centre; one pixel is
    `pixel_size` world units."""
    centre: np.ndarray    # (3,)
    axes: np.ndarray      # (3, 3) rows: right, up, back (unit, right-handed)
    pixel_size: float
    size: int             # the image is size x size pixels

    @classmethod
    def looking(cls, centre, forward, up, width, size=512):
        """A camera looking along -forward (so it sees the side of the mesh facing `forward`),
        image up along `up` (made perpendicular), `width` world units across the image."""
        back = np.asarray(forward, float) / np.linalg.norm(forward)
        up = np.asarray(up, float) - back * np.dot(up, back)
        up /= np.linalg.norm(up)
        right = np.cross(up, back)
        return cls(np.asarray(centre, float), np.stack([right, up, back]), float(width) / size, size)

    def project(self, points):
        """(k, 3) world points -> (k, 3): image x, y in pixels and depth towards the viewer."""
        local = (np.asarray(points, float) - self.centre) @ self.axes.T
        half = (self.size - 1) / 2.0
        return np.column_stack([half + local[:, 0] / self.pixel_size,
                                half - local[:, 1] / self.pixel_size, local[:, 2]])

    def ray_origins(self, pixels):
        """(k, 2) image points -> (k, 3) world points on the plane through the centre that faces
        the camera (the rays go along -back from there)."""
        half = (self.size - 1) / 2.0
        pixels = np.asarray(pixels, float)
        return (self.centre + np.outer((pixels[:, 0] - half) * self.pixel_size, self.axes[0])
                - np.outer((pixels[:, 1] - half) * self.pixel_size, self.axes[1]))


@dataclass(frozen=True)
class Render:
    image: np.ndarray     # (size, size, 3) uint8 BGR, black background (None: not shaded)
    triangle: np.ndarray  # (size, size) int32: the triangle seen at each pixel, -1 for background
    camera: Camera
    vertices: np.ndarray  # the mesh rendered (world space)
    triangles: np.ndarray
    projected: np.ndarray  # its vertices through the camera (Camera.project)

    def surface_points(self, pixels):
        """(k, 2) image points -> ((k, 3) world points on the surface, (k,) triangle ids).

        The triangle is the one seen at the nearest pixel; the point is where the pixel's ray
        meets it (barycentric coordinates from the projection, clamped into the triangle). A
        point on the background or outside the image gets NaN and -1."""
        pixels = np.asarray(pixels, float)
        k = len(pixels)
        points, ids = np.full((k, 3), np.nan), np.full(k, -1, dtype=np.int64)
        finite = np.all(np.isfinite(pixels), axis=1)
        cols = np.zeros(k, dtype=np.int64)
        rows = np.zeros(k, dtype=np.int64)
        cols[finite] = np.rint(pixels[finite, 0])
        rows[finite] = np.rint(pixels[finite, 1])
        inside = finite & (cols >= 0) & (cols < self.camera.size) & (rows >= 0) & (rows < self.camera.size)
        ids[inside] = self.triangle[rows[inside], cols[inside]]
        hit = ids >= 0
        corners = self.triangles[ids[hit]]                                 # (h, 3)
        flat = self.projected[corners][:, :, :2]
        weights = np.clip(_barycentric(flat, pixels[hit]), 0.0, None)
        weights /= weights.sum(axis=1, keepdims=True)
        points[hit] = np.einsum("hc,hcd->hd", weights, self.vertices[corners])
        return points, ids


def _barycentric(flat, points):
    """(h, 3) barycentric coordinates of 2-D points (h, 2) in 2-D triangles (h, 3, 2); a
    degenerate triangle gives its first corner."""
    e1, e2 = flat[:, 1] - flat[:, 0], flat[:, 2] - flat[:, 0]
    d = points - flat[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    safe = np.where(np.abs(det) > 1e-12, det, 1.0)
    b1 = np.where(det != 0, (d[:, 0] * e2[:, 1] - d[:, 1] * e2[:, 0]) / safe, 0.0)
    b2 = np.where(det != 0, (e1[:, 0] * d[:, 1] - e1[:, 1] * d[:, 0]) / safe, 0.0)
    return np.column_stack([1.0 - b1 - b2, b1, b2])


def render(vertices, triangles, camera, normals=None, shaded=True):
    """Render a mesh (world-space (n, 3) vertices, (m, 3) triangles) through `camera`.

    normals: (n, 3) vertex normals for the shading (default: area-weighted, core.mesh); pass the
    welded mesh's so split seams do not show as creases. shaded=False: no image (None), for a
    caller that reads only which triangle each pixel sees."""
    vertices = np.asarray(vertices, float)
    triangles = np.asarray(triangles, dtype=np.int64)
    if normals is None and shaded:
        normals = vertex_normals(vertices, triangles)
    projected = camera.project(vertices)
    size = camera.size
    depth = np.full(size * size, -np.inf)
    winner = np.full(size * size, -1, dtype=np.int64)
    weights = np.zeros((size * size, 3))
    low, extent = _pixel_boxes(projected[triangles], size)
    count = extent[:, 0] * extent[:, 1]
    for batch in _batches(count):
        _rasterise(projected[triangles[batch]], batch, low[batch], extent[batch], size,
                   depth, winner, weights)
    return Render(image=_shading(weights, winner, normals, triangles, camera) if shaded else None,
                  triangle=winner.astype(np.int32).reshape(size, size), camera=camera,
                  vertices=vertices, triangles=triangles, projected=projected)


def _shading(weights, winner, normals, triangles, camera):
    """(size, size, 3) uint8 BGR: SKIN_BGR under a headlight where a triangle is seen (its
    vertex normals interpolated by the pixel's barycentric weights), black elsewhere."""
    seen = winner >= 0
    normal = np.einsum("pc,pcd->pd", weights[seen], normals[triangles[winner[seen]]])
    length = np.linalg.norm(normal, axis=1)
    light = np.abs(normal @ camera.axes[2]) / np.maximum(length, 1e-12)
    image = np.zeros((camera.size * camera.size, 3))
    image[seen] = SKIN_BGR * (AMBIENT + (1.0 - AMBIENT) * light)[:, None]
    return np.clip(image, 0, 255).astype(np.uint8).reshape(camera.size, camera.size, 3)


def _pixel_boxes(corners, size):
    """Per triangle (projected corners (m, 3, 3)): the first pixel column and row whose centre
    may be inside it, and how many columns and rows."""
    xy = corners[:, :, :2]
    smallest = np.minimum(np.minimum(xy[:, 0], xy[:, 1]), xy[:, 2])   # faster than min(axis=1)
    largest = np.maximum(np.maximum(xy[:, 0], xy[:, 1]), xy[:, 2])
    low = np.clip(np.ceil(smallest), 0, size).astype(np.int64)
    high = np.clip(np.floor(largest), -1, size - 1).astype(np.int64)
    return low, np.maximum(high - low + 1, 0)


def _batches(count):
    """Ids of the triangles with candidate pixels (count per triangle), in batches of at most
    PAIRS_PER_BATCH candidates (a bigger triangle is a batch of its own)."""
    candidates = np.flatnonzero(count > 0)
    cumulative = np.cumsum(count[candidates])
    total = cumulative[-1] if len(cumulative) else 0
    starts = np.searchsorted(cumulative, np.arange(0, total, PAIRS_PER_BATCH), side="right")
    bounds = np.unique(np.concatenate([starts, [len(candidates)]]))
    return [candidates[a:b] for a, b in zip(bounds[:-1], bounds[1:]) if b > a]


def _plane_coefficients(corners):
    """(b, 3, 3) affine coefficients (of x, y, 1) per triangle of its 2nd and 3rd barycentric
    coordinates and its depth, from projected corners (b, 3, 3); degenerate triangles get
    coefficients that put every pixel outside."""
    e1, e2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    good = np.abs(det) > 1e-12
    inv = np.where(good, 1.0 / np.where(good, det, 1.0), 0.0)
    x0, y0 = corners[:, 0, 0], corners[:, 0, 1]
    # b1 = ((x - x0) e2y - (y - y0) e2x) / det, b2 = ((y - y0) e1x - (x - x0) e1y) / det
    b1 = np.stack([e2[:, 1], -e2[:, 0], -x0 * e2[:, 1] + y0 * e2[:, 0]], axis=1) * inv[:, None]
    b2 = np.stack([-e1[:, 1], e1[:, 0], x0 * e1[:, 1] - y0 * e1[:, 0]], axis=1) * inv[:, None]
    b1[~good] = (0.0, 0.0, -1.0)
    z = (corners[:, 0, 2, None] * (np.eye(3)[2] - b1 - b2) + corners[:, 1, 2, None] * b1
         + corners[:, 2, 2, None] * b2)
    return np.stack([b1, b2, z], axis=1)


def _affine(coefficients, owner, x, y):
    """Per pair: coefficients[owner] . (x, y, 1)."""
    return coefficients[owner, 0] * x + coefficients[owner, 1] * y + coefficients[owner, 2]


def _rasterise(corners, ids, low, extent, size, depth, winner, weights):
    """Z-buffer one batch of triangles (ids, projected corners, pixel boxes) into depth, winner
    and weights (flat per-pixel buffers)."""
    count = extent[:, 0] * extent[:, 1]
    owner = np.repeat(np.arange(len(ids), dtype=np.int32), count)
    local = np.arange(count.sum(), dtype=np.int32) - np.repeat(
        (np.cumsum(count) - count).astype(np.int32), count)
    width = extent[:, 0].astype(np.int32)[owner]
    cols = low[:, 0].astype(np.int32)[owner] + local % width
    rows = low[:, 1].astype(np.int32)[owner] + local // width
    # float32 halves the memory traffic; its rounding moves an edge by far less than a pixel
    planes = _plane_coefficients(corners).astype(np.float32)             # (b, 3, 3)
    x, y = cols.astype(np.float32), rows.astype(np.float32)
    b1 = _affine(planes[:, 0], owner, x, y)
    b2 = _affine(planes[:, 1], owner, x, y)
    inside = (b1 >= -1e-6) & (b2 >= -1e-6) & (b1 + b2 <= 1.0 + 1e-6)
    owner, x, y, b1, b2 = owner[inside], x[inside], y[inside], b1[inside], b2[inside]
    pixel = (rows * size + cols)[inside]
    z = _affine(planes[:, 2], owner, x, y).astype(np.float64)
    np.maximum.at(depth, pixel, z)
    won = z >= depth[pixel]       # the nearest in its pixel (or as near as what is there)
    pixel = pixel[won]
    winner[pixel] = ids[owner[won]]
    weights[pixel] = np.column_stack([1.0 - b1[won] - b2[won], b1[won], b2[won]])
