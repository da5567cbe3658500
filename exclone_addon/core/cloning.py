"""The whole cloning pipeline: landmarks -> registration -> correspondence -> transfer."""
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from . import deformation
from .correspondence import map_vertices, mapped_triangles, triangle_correspondence
from .errors import ExCloneError
from .landmarks import automatic_landmarks, checked_pairs
from .mesh import checked_triangles, diagonal, outward_sign, vertex_normals, vertex_parts
from .orientation import face_frame
from .registration import Schedule, register, similarity_icp, similarity_transform
from .transfer import Transfer


@dataclass
class CloneSettings:
    preset: str = "balanced"          # "fast" | "balanced" | "precise": registration schedule
    formulation: str = "reduced"      # "reduced" (2-edge QR gradient) | "augmented" (4th vertex)
    max_distance: float = 0.05        # correspondence / closest-point cut-off, x target diagonal
    landmark_weight: float = 0.1      # automatic landmarks are soft: a light pull per landmark
    correspondence: str = "vertex"    # "vertex" (vertex map, pairs elsewhere) | "triangle" (pairs only)


@dataclass
class CloneResult:
    names: list                       # expression names, in the order of `deltas`
    deltas: np.ndarray                # (E, n_target, 3) displacements in the target's own coordinates
    source_landmarks: np.ndarray      # (K,) source vertex ids
    target_landmarks: np.ndarray      # (K,) target vertex ids
    landmark_names: list              # (K,) names, e.g. "nose_tip"
    registered_source: np.ndarray     # (n_source, 3) source neutral deformed onto the target
    timings: dict = field(default_factory=dict)   # seconds per phase
    quality: dict = field(default_factory=dict)   # e.g. registration_mean_distance_rel


def _parts_of(ids, n_vertices, triangles):
    """Triangles of the connected parts that hold any of the vertices `ids`."""
    parts = vertex_parts(n_vertices, triangles)
    keep = np.isin(parts, parts[ids])
    return triangles[keep[triangles[:, 0]]]


@dataclass
class FaceFit:
    """Registration and correspondence of a source face onto a target: all the transfer needs.

    One fit serves any number of transfers (e.g. Register, then Clone of a chosen subset)."""
    source_vertex_count: int
    target: object                    # PolyMesh
    target_region: np.ndarray         # (T, 3) the target triangles that get gradients
    source_region: np.ndarray         # (S, 3) the registered source triangles
    rotation: np.ndarray              # (3, 3) \
    scale: float                      #          > similarity source -> target frame
    aligned_source: np.ndarray        # (n_source, 3) the source neutral after that similarity
    vertex_map: object                # correspondence.VertexMap of target vertices onto the source
    mapped: np.ndarray                # (T,) target triangles that take their image's gradient
    pairs: object                     # (T, S) sparse triangle pairs (elsewhere)
    weights: np.ndarray               # (T,) each target triangle's weight in the transfer
    formulation: str
    source_landmarks: np.ndarray
    target_landmarks: np.ndarray
    landmark_names: list
    registered_source: np.ndarray
    timings: dict = field(default_factory=dict)
    quality: dict = field(default_factory=dict)
    _transfer: object = None          # the factorised system, made on the first transfer


def fit_faces(source, target, *, landmarks=None, source_landmarks=None, settings=None,
              progress=None):
    """Landmarks, registration and correspondence of source onto target (PolyMesh each).

    landmarks: None for automatic ones, or {"source": ids, "target": ids} (same length; hard).
    source_landmarks: with automatic landmarks, the source's found before as (names, ids) (the
    bundled library ships its own): only the target's are looked for.
    progress: optional callable(fraction, message); it may raise core.errors.Cancelled.
    Raises ExCloneError with a user-facing message on bad input.
    """
    settings = settings or CloneSettings()
    if settings.formulation not in deformation.FORMULATIONS:
        raise ExCloneError(f"unknown formulation {settings.formulation!r}")
    timings = {}
    clock = time.perf_counter()

    def lap(name):
        nonlocal clock
        now = time.perf_counter()
        timings[name] = now - clock
        clock = now

    def report(fraction, message):
        if progress:
            progress(fraction, message)

    src_v, src_tris = checked_triangles(source, "source mesh")
    tgt_v, tgt_tris = checked_triangles(target, "target mesh")

    # 1. Landmarks
    report(0.0, "landmarks")
    if landmarks is None:
        if source_landmarks is not None:
            src_names, src_ids = list(source_landmarks[0]), np.asarray(source_landmarks[1])
            if len(src_names) != len(src_ids) or np.any(src_ids < 0) or np.any(src_ids >= len(src_v)):
                raise ExCloneError("the source's landmarks do not fit its mesh")

        def find(vertices, triangles):
            return automatic_landmarks(vertices, triangles, face_frame(vertices, triangles))

        # both faces at once when both are looked for (numpy and the KD-tree release the GIL);
        # the source's error, if any, is the one reported
        with ThreadPoolExecutor(max_workers=2) as pool:
            src_job = pool.submit(find, src_v, src_tris) if source_landmarks is None else None
            tgt_job = pool.submit(find, tgt_v, tgt_tris)
            if src_job:
                src_names, src_ids = src_job.result()
            tgt_names, tgt_ids = tgt_job.result()
        common = [n for n in src_names if n in tgt_names]
        src_lm = np.array([src_ids[src_names.index(n)] for n in common])
        tgt_lm = np.array([tgt_ids[tgt_names.index(n)] for n in common])
        landmark_names = common
    else:
        src_lm, tgt_lm = checked_pairs(landmarks, len(src_v), len(tgt_v))
        landmark_names = [f"landmark_{k}" for k in range(len(src_lm))]
    lap("landmarks")

    # 2. Registration of the source parts the landmarks are on, in the target's frame
    report(0.2, "registration")
    src_region = _parts_of(src_lm, len(src_v), src_tris)
    tgt_region = _parts_of(tgt_lm, len(tgt_v), tgt_tris)
    rot, scale, shift = similarity_transform(src_v[src_lm], tgt_v[tgt_lm])
    aligned = src_v @ rot.T * scale + shift
    src_sign = outward_sign(aligned, src_region)
    tgt_sign = outward_sign(tgt_v, tgt_region)
    diag = diagonal(tgt_v, np.unique(tgt_region))
    schedule = Schedule.preset(settings.preset)
    schedule.max_distance = settings.max_distance
    if landmarks is None:
        # Automatic landmarks are approximate: they start the alignment, the surfaces finish it
        # (a similarity ICP), and they guide the non-rigid fit softly.
        normals = src_sign * vertex_normals(aligned, src_region)
        region_ids = np.unique(src_region)
        r2, s2, t2 = similarity_icp(aligned[region_ids], normals[region_ids], tgt_v, tgt_region,
                                    tgt_sign, settings.max_distance * diag)
        aligned = aligned @ r2.T * s2 + t2
        rot, scale = r2 @ rot, s2 * scale
        schedule.landmark_weight = settings.landmark_weight

    def registration_progress(fraction, message):
        report(0.2 + 0.65 * fraction, message)

    reg = register(aligned, src_region, tgt_v, tgt_region, src_lm, tgt_v[tgt_lm],
                   formulation=settings.formulation, schedule=schedule,
                   source_normal_sign=src_sign, target_normal_sign=tgt_sign,
                   progress=registration_progress)
    lap("registration")
    if reg.valid_fraction < 0.3:
        raise ExCloneError(
            f"registration did not converge: only {100 * reg.valid_fraction:.0f}% of the source "
            "face found the target surface; check the landmarks")

    # 3. Correspondence: the vertex map where plausible, triangle pairs elsewhere
    report(0.85, "correspondence")
    vertex_map, mapped, pairs, weights = _correspond(reg.vertices, src_region, tgt_v, tgt_region,
                                                     src_sign, tgt_sign, diag, settings)
    lap("correspondence")
    quality = {
        "registration_mean_distance": reg.mean_distance,
        "registration_mean_distance_rel": reg.mean_distance / diag,
        "registration_valid_fraction": reg.valid_fraction,
        "registration_history_rel": [h / diag for h in reg.history],
        "correspondence_coverage": float(np.mean(weights > 0)),
        "correspondence_vertex_mapped": float(np.mean(mapped)),
        "landmark_count": int(len(src_lm)),
        "similarity_scale": scale,
        "target_diagonal": diag,
    }
    report(1.0, "fitted")
    return FaceFit(len(src_v), target, tgt_region, src_region, rot, scale, aligned, vertex_map,
                   mapped, pairs, weights, settings.formulation, src_lm, tgt_lm, landmark_names,
                   reg.vertices, timings, quality)


def _correspond(registered, src_region, tgt_v, tgt_region, src_sign, tgt_sign, diag, settings):
    """Correspondence of the target region with the registered source region: the vertex map
    where plausible, triangle pairs elsewhere. Returns (vertex_map, mapped, pairs, weights)."""
    max_distance = settings.max_distance * diag
    tgt_normals = tgt_sign * vertex_normals(tgt_v, tgt_region)
    vertex_map = map_vertices(registered, src_region, tgt_v, tgt_normals, np.unique(tgt_region),
                              max_distance, src_sign)
    if settings.correspondence == "vertex":
        mapped = mapped_triangles(vertex_map, registered, src_region, tgt_v, tgt_region,
                                  src_sign, tgt_sign)
    else:
        mapped = np.zeros(len(tgt_region), dtype=bool)
    pairs = triangle_correspondence(registered, src_region, tgt_v, tgt_region, max_distance,
                                    src_sign, tgt_sign, wanted=~mapped)
    pairs = pairs.matrix(len(tgt_region), len(src_region))
    weights = np.where(mapped, 1.0, np.asarray(pairs.sum(axis=1)).ravel())
    if not np.any(weights > 0):
        raise ExCloneError("no triangle of the target corresponds to the source; check the landmarks")
    return vertex_map, mapped, pairs, weights


def fit_registered(source, target, registered_source, *, settings=None):
    """A FaceFit from a registration made elsewhere (a known answer, or another tool's wrap of
    the source onto the target): correspondence only, no landmarks, no registration.

    registered_source: (n_source, 3) the source neutral deformed onto the target, in the
    target's coordinates. Every valid triangle of both meshes takes part. The similarity that
    brings the source's expressions into the target's frame is the least-squares one from the
    source to its registered positions.
    """
    settings = settings or CloneSettings()
    start = time.perf_counter()
    src_v, src_region = checked_triangles(source, "source mesh")
    tgt_v, tgt_region = checked_triangles(target, "target mesh")
    registered = np.asarray(registered_source, dtype=np.float64)
    if registered.shape != src_v.shape or not np.all(np.isfinite(registered)):
        raise ExCloneError(f"the registered source has shape {registered.shape} or invalid values; "
                           f"expected {src_v.shape} finite positions")
    ids = np.unique(src_region)
    rot, scale, shift = similarity_transform(src_v[ids], registered[ids])
    aligned = src_v @ rot.T * scale + shift
    src_sign, tgt_sign = outward_sign(aligned, src_region), outward_sign(tgt_v, tgt_region)
    diag = diagonal(tgt_v, np.unique(tgt_region))
    vertex_map, mapped, pairs, weights = _correspond(registered, src_region, tgt_v, tgt_region,
                                                     src_sign, tgt_sign, diag, settings)
    quality = {"correspondence_coverage": float(np.mean(weights > 0)),
               "correspondence_vertex_mapped": float(np.mean(mapped)),
               "similarity_scale": scale, "target_diagonal": diag}
    none = np.zeros(0, dtype=np.int64)
    return FaceFit(len(src_v), target, tgt_region, src_region, rot, scale, aligned, vertex_map,
                   mapped, pairs, weights, settings.formulation, none, none, [], registered,
                   {"correspondence": time.perf_counter() - start}, quality)


def _checked_deltas(source_deltas, names, n_source):
    deltas = np.asarray(source_deltas, dtype=np.float64)
    if deltas.ndim != 3 or deltas.shape[1:] != (n_source, 3):
        raise ExCloneError(f"expression deltas have shape {deltas.shape}; expected (E, {n_source}, 3)")
    if len(names) != len(deltas):
        raise ExCloneError(f"{len(names)} names for {len(deltas)} expressions")
    if not np.all(np.isfinite(deltas)):
        raise ExCloneError("source expressions contain NaN or infinite values")
    return deltas


def transfer_expressions(fit, source_deltas, names):
    """Every source expression onto the fitted target: CloneResult (timings and quality include
    the fit's). The transfer system is factorised once per fit and reused by later calls."""
    start = time.perf_counter()
    deltas = _checked_deltas(source_deltas, names, fit.source_vertex_count)
    tgt_v = np.asarray(fit.target.vertices, dtype=np.float64)
    tgt_region, src_region, mapped = fit.target_region, fit.source_region, fit.mapped
    aligned_deltas = deltas @ fit.rotation.T * fit.scale
    # the source at each mapped target vertex, sampled once: rest position and displacements
    anchors = np.flatnonzero(fit.vertex_map.valid)
    rest_at = np.zeros((len(tgt_v), 3))
    moves_at = np.zeros((len(deltas), len(tgt_v), 3))
    rest_at[anchors] = fit.vertex_map.sample(fit.aligned_source, src_region, anchors)
    moves_at[:, anchors] = np.moveaxis(
        fit.vertex_map.sample(np.moveaxis(aligned_deltas, 0, 1), src_region, anchors), 1, 0)
    wanted = np.zeros((len(deltas), len(tgt_region), 3, 3))
    if mapped.any():
        corners = tgt_region[mapped]
        rest = rest_at[corners]                                                 # (m, 3, 3)
        wanted[:, mapped] = deformation.corner_gradients(rest, rest + moves_at[:, corners])
    paired = ~mapped & (fit.weights > 0)
    if paired.any():
        rows = fit.pairs[paired]
        used = np.unique(rows.indices)              # only the source triangles some pair uses
        gradients = deformation.full_gradients(fit.aligned_source, fit.aligned_source + aligned_deltas,
                                               src_region[used])
        flat = np.moveaxis(gradients, 0, 1).reshape(len(used), -1)                  # (U, E*9)
        mean = (rows[:, used] @ flat) / fit.weights[paired, None]
        wanted[:, paired] = np.moveaxis(mean.reshape(-1, len(deltas), 3, 3), 1, 0)
    if fit._transfer is None:
        fit._transfer = Transfer(tgt_v, tgt_region, fit.weights, fit.formulation)
    result = fit._transfer(wanted, moves_at[:, anchors], anchors)
    _follow_unsolved(result, tgt_v, fit.target.triangles(), tgt_region)
    if not np.all(np.isfinite(result)):
        raise ExCloneError("transfer produced invalid values (NaN); the target mesh may be broken")
    timings = dict(fit.timings, transfer=time.perf_counter() - start)
    timings["total"] = sum(timings.values())
    return CloneResult(list(names), result, fit.source_landmarks, fit.target_landmarks,
                       fit.landmark_names, fit.registered_source, timings, dict(fit.quality))


def clone_expressions(source, source_deltas, names, target, *, landmarks=None,
                      source_landmarks=None, settings=None, progress=None):
    """Clone every source expression onto the target: fit_faces, then transfer_expressions.

    source, target: PolyMesh. source_deltas: (E, n_source, 3). names: E strings.
    landmarks, source_landmarks, progress: as fit_faces.
    Raises ExCloneError with a user-facing message on bad input.
    """
    deltas = _checked_deltas(source_deltas, names, len(source.vertices))   # before the long part

    def fit_progress(fraction, message):
        if progress:
            progress(0.8 * fraction, message)

    fit = fit_faces(source, target, landmarks=landmarks, source_landmarks=source_landmarks,
                    settings=settings, progress=fit_progress)
    if progress:
        progress(0.8, "transfer")
    result = transfer_expressions(fit, deltas, names)
    if progress:
        progress(1.0, "done")
    return result


# A separate part follows the face only if it comes this close to it (x the solved region's
# bounding-box diagonal): eyes, teeth and lashes do; a prop or a second body does not.
FOLLOW_REACH = 0.1


def _follow_unsolved(result, vertices, all_tris, used_tris):
    """Vertices the transfer did not solve follow the solved ones next to them.

    In a solved part (only on degenerate, skipped triangles) a vertex copies its nearest solved
    vertex. A separate part without landmarks (an eyeball, teeth) moves as a rigid body: the
    rotation and translation that best carry the solved vertices nearest to it (its anchors),
    so it keeps its shape (teeth follow the jaw, eyes the lids around them); a part further than
    FOLLOW_REACH from the face stays where it is.
    """
    solved = np.unique(used_tris)
    orphans = np.setdiff1d(np.unique(all_tris), solved)
    if not len(orphans):
        return
    gap, nearest = cKDTree(vertices[solved]).query(vertices[orphans])
    anchors = solved[nearest]
    parts = vertex_parts(len(vertices), all_tris)
    in_solved_part = np.isin(parts[orphans], parts[solved])
    result[:, orphans[in_solved_part]] = result[:, anchors[in_solved_part]]
    reach = FOLLOW_REACH * diagonal(vertices, solved)
    for part in np.unique(parts[orphans[~in_solved_part]]):
        mine = parts[orphans] == part
        if gap[mine].min() > reach:          # away from the face (a prop): it stays
            continue
        members, ref = orphans[mine], np.unique(anchors[mine])
        if len(ref) < 3:                                  # too few anchors to fix a rotation
            result[:, members] = result[:, ref].mean(axis=1, keepdims=True)
            continue
        rest = vertices[ref]
        centre = rest.mean(axis=0)
        for e in range(len(result)):
            moved = rest + result[e, ref]
            moved_centre = moved.mean(axis=0)
            rotation, _ = Rotation.align_vectors(moved - moved_centre, rest - centre)
            result[e, members] = (rotation.apply(vertices[members] - centre) + moved_centre
                                  - vertices[members])
