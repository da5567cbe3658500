"""Automatic corresponding landmarks (docs/method.md §4).

Fourteen points by geometric heuristics on the face's canonical frame (core.orientation: +X the
character's left, +Y up, +Z forward), walking surface profiles: the mid-sagittal profile (front-most
vertex per height bin near x = 0) and horizontal profiles through the nose tip and the nose bridge.
Where the eye has an opening in the skin, its ends give the eye corners and a vertical profile
through it the upper lid. Then the rest by an RBF with a linear term from a template face's
heuristic points to the mesh's, snapped to the mesh. Points that do not exist (a mask has no back
of head, no ear tips) are left out.
"""
import numpy as np
from scipy.interpolate import RBFInterpolator
from scipy.ndimage import uniform_filter1d
from scipy.signal import find_peaks
from scipy.spatial import cKDTree

from . import data
from .errors import ExCloneError
from .mesh import outward_sign, vertex_normals, vertex_parts
from .orientation import face_frame

HEURISTIC = (
    "nose_tip", "head_top", "ear_tip_left", "ear_tip_right", "nose_bridge", "alar_left",
    "alar_right", "upper_lip", "lower_lip", "subnasal", "chin", "eye_inner_left",
    "eye_inner_right", "head_back",
)
# Template-only points and their iBUG-68 index on the template (ICT-FaceKit's landmarks68).
TEMPLATE_IBUG = {
    "eye_outer_left": 45, "eye_outer_right": 36, "mouth_corner_left": 54,
    "mouth_corner_right": 48, "brow_mid_left": 24, "brow_mid_right": 19,
    "brow_outer_left": 26, "brow_outer_right": 17, "jaw_left": 12, "jaw_right": 4,
    "eyelid_upper_left": 44, "eyelid_upper_right": 37,
}
NAMES = HEURISTIC + tuple(TEMPLATE_IBUG)
# Template points placed by their surface direction rather than their position: the jaw point
# lies on a smoothly turning cheek where the spline's position slides along the surface, while
# its normal (iBUG 12's: about 72 degrees to the side, 21 down) says where it is.
NORMAL_PLACED = ("jaw_left", "jaw_right")
# The heuristic points that carry the template's: the ones that stay put when the face turns
# (the crown, the back of the head and the alar creases slide along flat or shallow shapes).
RBF_SOURCES = ("nose_tip", "nose_bridge", "subnasal", "upper_lip", "lower_lip",
               "eye_inner_left", "eye_inner_right", "eye_outer_left", "eye_outer_right",
               "ear_tip_left", "ear_tip_right")


def plane_section(points, triangles, axis, value):
    """Segments (m, 2, 3) where the triangles cut the plane points[:, axis] == value."""
    d = points[triangles, axis] - value                                  # (T, 3)
    a, b = np.array([0, 1, 2]), np.array([1, 2, 0])
    # a vertex exactly on the plane (a symmetric mesh's centre line) counts as above it, so the
    # triangles around it still cut the plane on two edges
    below = d < 0
    crosses = below[:, a] != below[:, b]                                 # (T, 3) edges
    cut = np.flatnonzero(crosses.sum(axis=1) == 2)
    tri, da, db = triangles[cut], d[cut][:, a], d[cut][:, b]
    t = np.divide(da, da - db, out=np.zeros_like(da), where=crosses[cut])
    pa, pb = points[tri[:, a]], points[tri[:, b]]
    hits = pa + t[..., None] * (pb - pa)                                 # (m, 3 edges, 3)
    order = np.argsort(~crosses[cut], axis=1, kind="stable")[:, :2]      # the two crossing edges
    return np.take_along_axis(hits, order[..., None], axis=1)


def _spanning(points, triangles, axis, low, high):
    """The triangles that reach into low <= points[:, axis] <= high: every triangle a cut
    (plane_section) within that band can cross, found once for a series of cuts."""
    values = points[triangles, axis]
    return triangles[(values.max(axis=1) >= low) & (values.min(axis=1) <= high)]


def _profile(segments, walk_axis, bin_size):
    """Front envelope (max z) of section segments sampled along `walk_axis`.

    Returns (sample positions, z (NaN where no segment), envelope point per sample)."""
    if len(segments) == 0:
        return np.zeros(0), np.zeros(0), np.zeros((0, 3))
    s0, s1 = segments[:, 0], segments[:, 1]
    lo = min(s0[:, walk_axis].min(), s1[:, walk_axis].min())
    hi = max(s0[:, walk_axis].max(), s1[:, walk_axis].max())
    centres = np.arange(lo + bin_size / 2, hi, bin_size)
    c0, c1 = s0[:, walk_axis][:, None], s1[:, walk_axis][:, None]       # (m, 1)
    with np.errstate(divide="ignore", invalid="ignore"):   # segments along the walk axis
        t = (centres[None, :] - c0) / (c1 - c0)                          # (m, B)
        inside = (t >= 0) & (t <= 1)
        z = np.where(inside, s0[:, 2:3] + t * (s1[:, 2:3] - s0[:, 2:3]), -np.inf)
    best = np.argmax(z, axis=0)
    cols = np.arange(len(centres))
    zmax = z[best, cols]
    tb = np.clip(t[best, cols], 0, 1)[:, None]
    pts = s0[best] + tb * (s1[best] - s0[best])
    empty = ~np.isfinite(zmax)
    zmax[empty] = np.nan
    pts[empty] = np.nan
    return centres, zmax, pts


def _walk(centres, zbin, pts, start, direction, prominence, smooth_bins):
    """Peaks and valleys of z met walking from `start` in `direction` (+1/-1) along a profile.

    Returns (peak points, valley points) in walking order; gaps (a hole such as the mouth) are
    bridged by interpolation, not stopped at.
    """
    keep = ~np.isnan(zbin)
    if keep.sum() < 5:
        return [], []
    z = uniform_filter1d(np.interp(centres, centres[keep], zbin[keep]), smooth_bins, mode="nearest")
    ahead = np.flatnonzero((centres - start) * direction > 0)
    if direction < 0:
        ahead = ahead[::-1]
    if len(ahead) < 3:
        return [], []
    real = np.flatnonzero(keep[ahead])
    if not len(real):    # only interpolation ahead: no surface point to give
        return [], []

    def nearest_real(k):
        return pts[ahead[real[np.argmin(np.abs(real - k))]]]

    peaks, _ = find_peaks(z[ahead], prominence=prominence)
    valleys, _ = find_peaks(-z[ahead], prominence=prominence)
    return [nearest_real(k) for k in peaks], [nearest_real(k) for k in valleys]


def _crease(profile, start, direction, near, far, prominence, smooth_bins, cliff=None):
    """A crease at walk distance [near, far] from `start`: the first z valley there; else, with
    `cliff`, the edge where z drops away by more than that between samples (an open eye socket);
    else the most concave bend (a crease that is only a knee on this face). None if no data."""
    centres, z, pts = profile
    keep = ~np.isnan(z)
    dist = (centres - start) * direction
    window = np.flatnonzero((dist >= near) & (dist <= far))
    if direction < 0:
        window = window[::-1]
    if keep.sum() < 5 or len(window) < 3:
        return None
    zs = uniform_filter1d(np.interp(centres, centres[keep], z[keep]), smooth_bins, mode="nearest")
    real = np.flatnonzero(keep)

    def nearest_real(k):
        return pts[real[np.argmin(np.abs(real - k))]]

    valleys, _ = find_peaks(-zs[window], prominence=prominence)
    if cliff is not None:
        drops = np.flatnonzero(np.diff(z[window]) < -cliff)
        if len(drops) and (not len(valleys) or drops[0] < valleys[0]):
            return nearest_real(window[drops[0]])
    if len(valleys):
        return nearest_real(window[valleys[0]])
    bend = np.gradient(np.gradient(zs))
    return nearest_real(window[np.argmax(bend[window])])


def _first_rise(profile, start, direction, near, far, cliff):
    """Walking a profile from `start` in `direction` (+1 or -1), the first sample between `near`
    and `far` from the start where the surface rises forward by more than `cliff` from the one
    before: where an opening (an eye socket, a hole) ends. None if there is no such rise."""
    centres, z, pts = profile
    dist = (centres - start) * direction
    window = np.flatnonzero((dist >= near) & (dist <= far) & ~np.isnan(z))
    if direction < 0:
        window = window[::-1]
    rises = np.flatnonzero(np.diff(z[window]) > cliff)
    return pts[window[rises[0] + 1]] if len(rises) else None


def _opening_end(q, triangles, start, direction, near, far, heights, bin_size, cliff):
    """Where an opening ends walking along x from x = start in `direction`: the _first_rise on
    each horizontal cut at `heights`, the furthest of those in `direction` (cuts above or below
    the opening have none), or None."""
    triangles = _spanning(q, triangles, 1, heights.min(), heights.max())
    ends = [_first_rise(_profile(plane_section(q, triangles, 1, height), 0, bin_size), start,
                        direction, near, far, cliff) for height in heights]
    ends = [end for end in ends if end is not None]
    return max(ends, key=lambda p: p[0] * direction) if ends else None


def _upper_lid(q, skin_triangles, inner, outer, nose_length, bin_size, cliff):
    """Walking up the skin through the middle of the eye, from the corners' height, the opening
    (a hole, a socket) ends where the surface rises forward by a cliff: the upper lid's margin.
    None if there is no such rise (closed lids)."""
    profile = _profile(plane_section(q, skin_triangles, 0, (inner[0] + outer[0]) / 2), 1, bin_size)
    return _first_rise(profile, (inner[1] + outer[1]) / 2, +1, -0.1 * nose_length,
                       0.8 * nose_length, cliff)


def _front_most(profile, low, high):
    """The profile's front-most point with walk coordinate in [low, high], or None."""
    centres, z, pts = profile
    window = np.flatnonzero((centres >= low) & (centres <= high) & ~np.isnan(z))
    return pts[window[np.argmax(z[window])]] if len(window) else None


# Profile sampling, in fractions of the face's diagonal: bins of 0.25%, peaks and valleys that
# stand out by 0.2%, an opening's edge where the surface jumps by 1% between bins.
BIN = 0.0025
PROMINENCE = 0.002
CLIFF = 0.01
SMOOTH_BINS = 3


def _not_found(what):
    return ExCloneError(f"could not find the face's {what}; place the landmarks by hand")


def heuristic_landmarks(vertices, triangles, frame=None, parts=None, nose_tip=None):
    """The heuristic landmarks that exist on this mesh: {name: vertex id}.
    parts: the vertices' connected part labels if already known (a surface.Surface's).
    nose_tip: the nose tip's vertex if known otherwise (a found face's), where the front-most
    point of the midline is not it (a stylised face whose lips stand out further than its nose):
    the profiles are walked from there.
    Raises ExCloneError where the mesh has no surface to look for them on."""
    frame = frame or face_frame(vertices, triangles)
    q = frame.to_canonical(vertices)
    used = np.unique(triangles)
    diag = frame.diagonal
    tip_id, near_mid = _nose_tip(q, used, diag)
    tip_id = tip_id if nose_tip is None else int(nose_tip)
    tip = q[tip_id]
    # The skin: the part the nose tip is on. Every point snaps to it, and the eye's points are
    # looked for on it alone (eyeballs, lashes and eye occluders sit in front of the opening).
    parts = vertex_parts(len(vertices), triangles) if parts is None else parts
    skin = used[parts[used] == parts[tip_id]]
    height = np.ptp(q[used, 1])
    found = {"nose_tip": tip}   # name -> canonical position (snapped to a vertex at the end)
    found.update(_head_extremes(q, used, near_mid, tip, height, diag))
    # Sections keep to the face side (in front of the ears' depth).
    front_tris = triangles[np.all(q[triangles, 2] > tip[2] - 0.3 * height, axis=1)]
    found.update(_profile_points(q, front_tris, tip, diag))
    if "nose_bridge" in found:
        skin_tris = front_tris[parts[front_tris[:, 0]] == parts[tip_id]]
        found.update(_beside_the_nose(q, front_tris, skin_tris, tip, found["nose_bridge"], diag))
    return _snap_symmetric(found, q, skin)


# The nose tip: the front-most midline vertex, unless one of the midline's bumps (each the
# front-most vertex within BUMP x the diagonal of itself) no more than TIP_DEPTH behind it and
# standing out of the surface within SURROUNDINGS of it at least STRONG as far as the bump that
# stands out most lies above it: then the uppermost such bump. A face whose lower lip reaches
# further forward than its nose has the lip front-most (ICT identity 6); the lips and the chin
# lie below the nose. Measured (stand-out x the diagonal): the noses 0.0156-0.0205, the lips
# 0.0135-0.0189, a chin 0.0040, the MakeHuman child's brow ridge, within TIP_DEPTH of its nose tip
# in its rendered face's frame, 0.0052 (within 0.08: 0.0243, as strong as its nose's 0.0274: the
# broad surroundings hide it). On the 468-point canonical face the front-most vertex (4) stands
# out 0.0095 and the one below it (1) 0.0137: the tip stays the front-most.
BUMP, TIP_DEPTH, SURROUNDINGS, STRONG = 0.02, 0.03, 0.04, 0.7


def _nose_tip(q, used, diag):
    """The nose tip (the front-most midline vertex, or the uppermost strong bump above it), and
    the vertices near the midline."""
    near_mid = used[np.abs(q[used, 0]) < 0.03 * diag]
    if not len(near_mid):
        raise _not_found("nose tip (no surface near its symmetry plane)")
    front = near_mid[q[near_mid, 2] >= q[near_mid, 2].max() - TIP_DEPTH * diag]
    # a front vertex is a bump unless one further forward lies within BUMP (any such is in front
    # too): the pairs within BUMP, each pair's hindmost struck out
    pairs = cKDTree(q[front]).query_pairs(BUMP * diag, output_type="ndarray")
    depth = q[front, 2]
    first, second = depth[pairs[:, 0]], depth[pairs[:, 1]]
    bump = np.ones(len(front), dtype=bool)
    bump[pairs[first < second, 0]] = False
    bump[pairs[second < first, 1]] = False
    bumps = front[bump]
    # each bump's surroundings measured directly: a few bumps, no tree over the whole surface
    surface, reach = q[used], (SURROUNDINGS * diag) ** 2
    stands_out = np.array([q[b, 2] - surface[((surface - q[b]) ** 2).sum(axis=1) <= reach, 2].mean()
                           for b in bumps])
    front_most = near_mid[np.argmax(q[near_mid, 2])]
    candidates = np.append(bumps[stands_out >= STRONG * stands_out.max()], front_most)
    return candidates[np.argmax(q[candidates, 1])], near_mid


def _head_extremes(q, used, near_mid, tip, height, diag):
    """The crown, the back of the head and the ear tips: {} unless the mesh wraps around (a
    head, not a mask), told by how deep the midline goes behind the nose."""
    band = near_mid[np.abs(q[near_mid, 1] - tip[1]) < 0.15 * diag]
    if not (band.size and (tip[2] - q[band, 2].min()) > 0.35 * height):
        return {}
    # the skull's midline only: a mesh may go on into neck and shoulders below the nose
    skull = near_mid[q[near_mid, 1] > tip[1]]
    if not len(skull):
        raise _not_found("skull (no surface above the nose on its midline)")
    ears = used[np.abs(q[used, 1] - tip[1]) < 0.12 * diag]
    # A flat back of the skull has no single extreme (a degree of tilt moves it by several
    # % of the head): the middle of the band within 0.5% of the diagonal of the rearmost.
    back = skull[q[skull, 2] < q[skull, 2].min() + 0.005 * diag]
    middle = np.argmin(np.linalg.norm(q[back] - q[back].mean(axis=0), axis=1))
    return {"head_top": q[used[np.argmax(q[used, 1])]], "head_back": q[back[middle]],
            "ear_tip_left": q[ears[np.argmax(q[ears, 0])]],
            "ear_tip_right": q[ears[np.argmin(q[ears, 0])]]}


def _profile_points(q, front_tris, tip, diag):
    """Along the mid-sagittal profile: the nose bridge, the subnasal point, the lips and the
    chin (those found)."""
    prominence = PROMINENCE * diag
    sag = _profile(plane_section(q, front_tris, 0, 0.0), 1, BIN * diag)
    found = {}
    # nose bridge (sellion): the crease between nose and forehead, a nose's length above the tip
    bridge = _crease(sag, tip[1], +1, 0.04 * diag, 0.2 * diag, prominence, SMOOTH_BINS)
    if bridge is not None:
        found["nose_bridge"] = bridge
    down_peaks, down_valleys = _walk(*sag, tip[1], -1, prominence, SMOOTH_BINS)
    if down_valleys:
        found["subnasal"] = down_valleys[0]
        below = [p for p in down_peaks if p[1] < down_valleys[0][1]]
        for name, p in zip(("upper_lip", "lower_lip"), below):
            found[name] = p
    if "lower_lip" in found and "nose_bridge" in found:
        # The chin barely stands out of the groove above it on many faces, so no peak test:
        # the front-most point in a window below the lower lip, scaled by the nose's length.
        nose_length = found["nose_bridge"][1] - tip[1]
        y = found["lower_lip"][1]
        chin = _front_most(sag, y - 1.0 * nose_length, y - 0.25 * nose_length)
        if chin is not None:
            found["chin"] = chin
    return found


def _beside_the_nose(q, front_tris, skin_tris, tip, bridge, diag):
    """On horizontal profiles, at nose-length-scaled distances from the midline on each side:
    the eye's points beside the bridge and the alar crease beside the nose (those found)."""
    nose_length = bridge[1] - tip[1]
    bin_size = BIN * diag
    # the inner corners sit at or somewhat below the bridge: cuts at several heights
    heights = bridge[1] - nose_length * np.linspace(0.0, 0.5, 21)
    band = _spanning(q, front_tris, 1, heights.min(), heights.max())
    eye_cuts = [_profile(plane_section(q, band, 1, height), 0, bin_size) for height in heights]
    # Alar creases: just below the tip's height, where a cut leaves the nose wing for the
    # cheek (not the nostril beside the columella, nearer the midline).
    alar = _profile(plane_section(q, front_tris, 1, tip[1] - 0.1 * nose_length), 0, bin_size)
    found = {}
    for direction, side in ((+1, "left"), (-1, "right")):
        eye = _eye(q, skin_tris, eye_cuts, direction, nose_length, diag)
        crease = _crease(alar, 0.0, direction, 0.2 * nose_length, 0.9 * nose_length, np.inf,
                         2 * SMOOTH_BINS)
        # the inner corner first, then the crease: the order the template file lists them in
        if "eye_inner" in eye:
            found[f"eye_inner_{side}"] = eye["eye_inner"]
        if crease is not None:
            found[f"alar_{side}"] = crease
        found.update({f"{name}_{side}": point for name, point in eye.items()})
    return found


def _eye(q, skin_tris, eye_cuts, direction, nose_length, diag):
    """One eye's inner and outer corners and upper lid, those found: {"eye_inner": point,
    "eye_outer": point, "eyelid_upper": point}. The inner corner is the deepest crease beside
    the bridge over the cuts, then the eye opening's far ends: the outer corner walking out from
    the crease, the inner one walking back in from the middle (both over cuts at several
    heights: one cut at the crease's height misses the opening when the face is tilted)."""
    cliff = CLIFF * diag
    bin_size = BIN * diag
    corners = [_crease(cut, 0.0, direction, 0.15 * nose_length, 0.9 * nose_length,
                       PROMINENCE * diag, SMOOTH_BINS, cliff=cliff) for cut in eye_cuts]
    corners = [c for c in corners if c is not None]
    if not corners:
        return {}
    corner = min(corners, key=lambda c: c[2])
    found = {"eye_inner": corner}
    outer = _opening_end(q, skin_tris, corner[0], direction, 0.3 * nose_length, 1.0 * nose_length,
                         corner[1] + nose_length * np.linspace(-0.1, 0.3, 9), bin_size, cliff)
    if outer is None:
        return found
    found["eye_outer"] = outer
    middle = (corner[0] + outer[0]) / 2
    inner = _opening_end(q, skin_tris, middle, -direction, 0.0,
                         (middle - corner[0]) * direction + 0.3 * nose_length,
                         corner[1] + nose_length * np.linspace(-0.1, 0.2, 9), bin_size, cliff)
    if inner is not None:
        corner = found["eye_inner"] = inner
    lid = _upper_lid(q, skin_tris, corner, outer, nose_length, bin_size, cliff)
    if lid is not None:
        found["eyelid_upper"] = lid
    return found


def _symmetric(found):
    """Canonical points or directions with each left/right pair made mirror-symmetric (each
    side the mean of itself and its mirrored twin): faces are nearly symmetric, and one side's
    detection noise should not make the two sides disagree."""
    points = dict(found)
    mirror = np.array([-1.0, 1.0, 1.0])
    for name in found:
        if name.endswith("_left") and name[:-5] + "_right" in found:
            right = name[:-5] + "_right"
            mean = (np.asarray(found[name]) + mirror * found[right]) / 2
            points[name], points[right] = mean, mirror * mean
    return points


def _snap_symmetric(found, q, candidates):
    """Snap canonical positions, made mirror-symmetric, to the nearest candidate vertices."""
    points = _symmetric(found)
    names = list(points)
    _, ids = cKDTree(q[candidates]).query(np.array([points[n] for n in names]))
    return {n: int(candidates[i]) for n, i in zip(names, ids)}


def _place_by_normal(found, wanted_normals, q, normals, candidates, radius):
    """For each canonical position, the candidate vertex within `radius` whose normal is nearest
    the wanted one (positions and normals made mirror-symmetric first); the nearest vertex if
    none is that close."""
    points = _symmetric(found)
    wanted = _symmetric({name: wanted_normals[name] for name in found})
    ids = {}
    for name, point in points.items():
        distance = np.linalg.norm(q[candidates] - point, axis=1)
        near = np.flatnonzero(distance < radius)
        pick = near[np.argmax(normals[candidates[near]] @ wanted[name])] if len(near) \
            else np.argmin(distance)
        ids[name] = int(candidates[pick])
    return ids


def _template():
    shipped = data.landmark_template()["canonical_positions"]
    return {name: np.array(position) for name, position in shipped.items()}


def _template_normals():
    shipped = data.landmark_template()["canonical_normals"]
    return {name: np.array(normal) for name, normal in shipped.items()}


# Fewer pairs than this cannot fix a similarity with any redundancy.
MIN_PAIRS = 4


def _whole_numbers(values):
    """int64 ids; ValueError for anything but whole numbers (4.5 or "7" is no vertex id)."""
    ids = np.asarray(values).ravel()
    if len(ids) and ids.dtype.kind not in "iu":
        raise ValueError(f"not whole numbers: {ids.dtype}")
    return ids.astype(np.int64)


def checked_pairs(pairs, n_source, n_target):
    """Landmark pairs {"source": [vertex ids], "target": [vertex ids]} (from a file, a panel or a
    caller) as two int64 arrays; ExCloneError saying what is wrong otherwise. The one check of
    landmark ids, whoever gives them."""
    try:
        src, tgt = _whole_numbers(pairs["source"]), _whole_numbers(pairs["target"])
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
        raise ExCloneError('landmarks must be {"source": [vertex ids], "target": [vertex ids]} '
                           "with whole-number ids") from exc
    if len(src) != len(tgt):
        raise ExCloneError(f"landmarks: {len(src)} source ids but {len(tgt)} target ids")
    if len(src) < MIN_PAIRS:
        raise ExCloneError(f"landmarks: {len(src)} pairs given, at least {MIN_PAIRS} are needed")
    return checked_ids(src, n_source, "source"), checked_ids(tgt, n_target, "target")


def checked_ids(ids, n, what):
    """One mesh's landmark vertex ids (int64) when each is a vertex of its `n` and none is used
    twice; ExCloneError naming `what` (the mesh) otherwise. checked_pairs' check of each side,
    also for ids stored with one mesh."""
    ids = np.asarray(ids, dtype=np.int64)
    if len(ids) and (ids.min() < 0 or ids.max() >= n):
        raise ExCloneError(f"landmarks: a {what} vertex id is outside 0..{n - 1}")
    if len(np.unique(ids)) != len(ids):
        raise ExCloneError(f"landmarks: a {what} vertex id is used twice")
    return ids


def automatic_landmarks(vertices, triangles, frame=None, template=None, template_normals=None,
                        surface=None, nose_tip=None):
    """Heuristic landmarks plus template ones: (names, vertex ids), in NAMES order.

    template: {name: canonical position}, template_normals: {name: canonical outward normal} of
    the NORMAL_PLACED points; the shipped ones by default. surface: the surface.Surface of these
    vertices and triangles if one is prepared (its parts and outward normals are used, not
    computed again). nose_tip: as heuristic_landmarks.
    Raises ExCloneError if too few heuristic points are found to place the template.
    """
    frame = frame or face_frame(vertices, triangles)
    parts = surface.parts if surface is not None else vertex_parts(len(vertices), triangles)
    found = heuristic_landmarks(vertices, triangles, frame, parts, nose_tip)
    template = template if template is not None else _template()
    template_normals = template_normals if template_normals is not None else _template_normals()
    shared = [n for n in RBF_SOURCES if n in found and n in template]
    if len(shared) < 6:
        missing = ", ".join(n for n in RBF_SOURCES if n not in found)
        raise ExCloneError(f"only {len(shared)} landmarks found automatically (missing: {missing}); "
                           "place the landmarks by hand")
    q = frame.to_canonical(vertices)
    src = np.array([template[n] for n in shared])
    dst = np.array([q[found[n]] for n in shared])
    # the linear term carries scale and shear between faces; the spline bends the rest
    rbf = RBFInterpolator(src, dst, kernel="thin_plate_spline", degree=1)
    # snap onto the parts the heuristic points are on (not eyeballs, teeth or lashes)
    on_face = np.flatnonzero(np.isin(parts, parts[list(found.values())]))
    extra = [n for n in TEMPLATE_IBUG if n in template and n not in found]
    mapped = dict(zip(extra, rbf(np.array([template[n] for n in extra]))))
    by_normal = {n: mapped.pop(n) for n in NORMAL_PLACED if n in mapped and n in template_normals}
    found.update(_snap_symmetric(mapped, q, on_face))
    if by_normal:
        # outward normals in the canonical frame (turning them agrees with recomputing them)
        normals = surface.vertex_normals @ frame.rotation if surface is not None \
            else outward_sign(q, triangles) * vertex_normals(q, triangles)
        found.update(_place_by_normal(by_normal, template_normals, q, normals, on_face,
                                      0.05 * frame.diagonal))
    names = [n for n in NAMES if n in found]
    return names, np.array([found[n] for n in names], dtype=np.int64)
