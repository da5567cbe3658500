"""The whole cloning pipeline (docs/method.md §1): landmarks -> rigid alignment -> registration
-> correspondence -> transfer.

fit_faces runs the first four once per source and target (a FaceFit); transfer_expressions
carries any number of expressions through a fit; clone_expressions does both. Each mesh is
welded by position (copies an exporter split at UV seams become one vertex, mesh.welded) and
prepared once as a surface.Surface passed from step to step; every copy of a vertex gets the
same motion. Ids and arrays in and out are in the caller's numbering.
"""
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from . import deformation, followers
from .correspondence import (Correspondence, VertexMap, map_vertices, mapped_triangles,
                             source_matches, triangle_correspondence)
from .errors import ExCloneError
from .landmarks import MIN_PAIRS, automatic_landmarks, checked_pairs
from .mesh import checked_triangles, triangle_areas, vertex_parts, welded
from .orientation import face_frame
from .registration import Schedule, register, similarity_icp, similarity_transform
from .reports import listed
from .rims import RimGoals
from .shape_space import fit_shape_space, plausible
from .surface import Surface
from .threads import limited_threads
from .transfer import CorrespondedTransfer, Transfer

CORRESPONDENCES = ("vertex", "triangle")


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
    # expression_measures.Openings of the rest target's eyes and lips as the rims found them
    # (welded numbering; None: not found), so that the measures need not find them again
    openings: object = None


@dataclass
class FaceFit:
    """Registration and correspondence of a source face onto a target: all the transfer needs.

    One fit serves any number of transfers (e.g. Register, then Clone of a chosen subset). The
    surfaces and solve arrays are in the welded numbering (mesh.welded); the landmarks and the
    registered source in the meshes' own."""
    source: object                    # surface.Surface of the welded source mesh, its own coordinates
    target: object                    # PolyMesh as given
    welded_target: object             # Welded: the target welded for the solve
    source_weld: object               # Welded: the source's
    target_region: object             # surface.Surface of the target triangles that get gradients
    source_region: np.ndarray         # (S, 3) the registered source triangles
    rotation: np.ndarray              # (3, 3) \
    scale: float                      #          > similarity source -> target frame
    aligned_source: np.ndarray        # (n_source, 3) the source neutral after that similarity
    vertex_map: object                # correspondence.VertexMap of target vertices onto the source
    mapped: np.ndarray                # (T,) target triangles that take their image's gradient
    pairs: object                     # (T, S) sparse triangle pairs (elsewhere)
    weights: np.ndarray               # (T,) each target triangle's weight in the transfer
    formulation: str
    source_landmarks: np.ndarray      # (K,) source vertex ids, the source's own numbering
    target_landmarks: np.ndarray      # (K,) target vertex ids, the target's own numbering
    landmark_names: list
    registered_source: np.ndarray     # (n_source, 3) in the source's own numbering
    timings: dict = field(default_factory=dict)
    quality: dict = field(default_factory=dict)
    # (k,) target vertices held at exactly zero displacement, welded numbering (e.g. the cut
    # border of a head cut out of a body); set before the first transfer
    fixed_vertices: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    _transfer: object = None          # the factorised system, made on the first transfer
    _rims: object = None              # rims.RimGoals of the eyes, made on the first transfer
    # the target region's deformation.gradient_operator, made by the fit where a thread would
    # only wait, for the first transfer (None: the transfer makes it)
    _gradient: object = None


@dataclass
class Welded:
    """A mesh welded by position for the solve (mesh.welded), and the way back to its own
    numbering."""
    surface: object                   # surface.Surface of the welded mesh's valid triangles
    mesh: object                      # the welded PolyMesh
    index: np.ndarray                 # (n,) welded id of each of the mesh's own vertices

    @cached_property
    def originals(self):
        """(k,) the first own vertex of each welded one."""
        return np.unique(self.index, return_index=True)[1]

    def own_count(self):
        return len(self.index)


# ------------------------------------------------------------------------------ fitting

@limited_threads
def fit_faces(source, target, *, landmarks=None, source_landmarks=None, settings=None,
              progress=None, face_guide=None, fixed_vertices=None, shared_vertices=None,
              source_modes=None):
    """Landmarks, registration and correspondence of source onto target (PolyMesh each).

    landmarks: None for automatic ones, or {"source": ids, "target": ids} (same length; hard).
    source_landmarks: with automatic landmarks, the source's found before as (names, ids) (the
    bundled library ships its own): only the target's are looked for.
    progress: optional callable(fraction, message); it may raise core.errors.Cancelled.
    face_guide: the target's face as found in images (core.character.FaceGuide, in the target's
    coordinates): the automatic landmarks use its frame and are cross-checked with its points.
    fixed_vertices: (k,) target vertex ids (its own numbering) every transfer holds still, e.g.
    the cut of a head taken out of a body (core.character.HeadCut.fixed).
    shared_vertices: for a target made from the source's base mesh (core.character.
    shared_vertices), _fit_shared's `shared`: with automatic landmarks the fit is _fit_shared's,
    no registration (edited landmarks ask for a registration that holds them).
    source_modes: (k, n_source, 3) how the source's neutral varies between faces (the bundled
    library's ExpressionLibrary.shape_modes), or None: the registration starts from the face of
    that space nearest the target (core.shape_space).
    Raises ExCloneError with a user-facing message on bad input.
    """
    return _fit(_welded_surface(source, "source mesh"), target, landmarks, source_landmarks,
                _checked_settings(settings), _progress_span(progress, 0.0, 1.0), face_guide,
                fixed_vertices, shared_vertices, source_modes)


def _fit(source_weld, target_mesh, landmarks, source_landmarks, settings, report,
         face_guide=None, fixed_vertices=None, shared_vertices=None, source_modes=None):
    """fit_faces on the welded source (Welded, whole mesh); report(fraction, message) or a
    no-op."""
    if shared_vertices is not None and landmarks is None:
        return _fit_shared(source_weld, target_mesh, shared_vertices, source_landmarks, settings,
                           fixed_vertices)
    stopwatch = _Stopwatch()
    target_weld = _welded_surface(target_mesh, "target mesh")
    source, target = source_weld.surface, target_weld.surface
    report(0.0, "landmarks")
    src_lm, tgt_lm, landmark_names, whole_gradient = _landmarks(
        source_weld, target_weld, landmarks, source_landmarks, face_guide, settings.formulation)
    stopwatch.lap("landmarks")

    report(0.2, "registration")
    source_region, target_region = source.parts_holding(src_lm), target.parts_holding(tgt_lm)
    automatic = landmarks is None
    rotation, scale, aligned = _rigid_alignment(source_region, target_region, src_lm, tgt_lm,
                                                automatic, settings)
    start, shape_quality = aligned, {}
    if source_modes is not None:
        rotation, scale, aligned, start, shape_quality = _shape_start(
            aligned, target_region, _checked_modes(source_modes, source_weld), rotation, scale,
            settings)
    reg = _registration(start, target_region, src_lm, tgt_lm, automatic, settings,
                        _progress_span(report, 0.2, 0.85))
    stopwatch.lap("registration")

    report(0.85, "correspondence")
    vertex_map, mapped, pairs, weights = _correspond(reg.surface, target_region, settings)
    stopwatch.lap("correspondence")
    report(1.0, "fitted")
    return FaceFit(
        source=source, target=target_mesh, welded_target=target_weld, source_weld=source_weld,
        target_region=target_region,
        source_region=source_region.triangles, rotation=rotation, scale=scale,
        aligned_source=aligned.vertices, vertex_map=vertex_map, mapped=mapped, pairs=pairs,
        weights=weights, formulation=settings.formulation,
        source_landmarks=source_weld.originals[src_lm],
        target_landmarks=target_weld.originals[tgt_lm], landmark_names=landmark_names,
        registered_source=reg.vertices[source_weld.index],
        timings=stopwatch.timings,
        quality={**_registration_quality(reg, target_region.diagonal, len(src_lm)),
                 **_correspondence_quality(mapped, weights, scale, target_region.diagonal),
                 **shape_quality},
        fixed_vertices=_welded_ids(target_weld, fixed_vertices),
        _gradient=_region_gradient(whole_gradient, target, target_region))


def _region_gradient(whole, target, region):
    """The target region's rows of the whole welded target's gradient operator `whole` (reduced
    formulation; None: not made), the region being whole connected parts of the target (its
    triangles in the target's order, Surface.parts_holding): each triangle's rows are its own."""
    if whole is None or region is target:
        return whole
    kept = np.isin(target.parts[target.triangles[:, 0]], target.parts[region.triangles[:, 0]])
    return whole[np.repeat(kept, 3)]


def _checked_settings(settings):
    """The settings (defaults if None), or ExCloneError naming what is valid."""
    settings = settings or CloneSettings()
    deformation.checked_formulation(settings.formulation)
    Schedule.preset(settings.preset)
    if settings.correspondence not in CORRESPONDENCES:
        raise ExCloneError(f"unknown correspondence {settings.correspondence!r}; use one of: "
                           + ", ".join(CORRESPONDENCES))
    for name in ("max_distance", "landmark_weight"):
        value = getattr(settings, name)
        try:
            usable = bool(np.isfinite(float(value)) and float(value) > 0)
        except (TypeError, ValueError):
            usable = False
        if not usable:
            raise ExCloneError(f"setting {name} is {value!r}; it must be a positive number")
    return settings


def _welded_surface(mesh, what):
    """The PolyMesh welded by position, with the Surface of its valid triangles (MeshError if
    the mesh cannot be used)."""
    welded_mesh, index = welded(mesh)
    return Welded(Surface(*checked_triangles(welded_mesh, what)), welded_mesh, index)


def _welded_ids(weld, ids):
    """(k,) unique welded ids of a mesh's own vertex ids (None: none); ExCloneError if any is
    not a vertex of it."""
    if ids is None:
        return np.zeros(0, dtype=np.int64)
    ids = np.asarray(ids, dtype=np.int64).ravel()
    if len(ids) and (ids.min() < 0 or ids.max() >= weld.own_count()):
        raise ExCloneError(f"a fixed vertex id is outside 0..{weld.own_count() - 1}")
    return np.unique(weld.index[ids])


def _landmarks(source_weld, target_weld, landmarks, source_landmarks, face_guide=None,
               formulation=deformation.REDUCED):
    """(source ids, target ids, names) in the welded numbering: the given pairs (the meshes'
    own ids), checked, or automatic ones (on the target with face_guide's help, if given); and
    the whole welded target's gradient operator in `formulation` where this thread made it while
    it would only wait (_prepare_for_fit), else None."""
    source, target = source_weld.surface, target_weld.surface
    if landmarks is not None:
        src_lm, tgt_lm = checked_pairs(landmarks, source_weld.own_count(), target_weld.own_count())
        return (source_weld.index[src_lm], target_weld.index[tgt_lm],
                [f"landmark_{k}" for k in range(len(src_lm))], None)
    if source_landmarks is not None:
        src_names, src_ids = list(source_landmarks[0]), np.asarray(source_landmarks[1])
        if len(src_names) != len(src_ids) or np.any(src_ids < 0) \
                or np.any(src_ids >= source_weld.own_count()):
            raise ExCloneError("the source's landmarks do not fit its mesh")
        src_ids = source_weld.index[src_ids]

    # both faces at once when both are looked for (numpy and the KD-tree release the GIL);
    # the source's error, if any, is the one reported
    gradient = None
    with ThreadPoolExecutor(max_workers=2) as pool:
        src_job = pool.submit(_found, source) if source_landmarks is None else None
        tgt_job = pool.submit(_found, target, face_guide)
        if src_job:
            src_names, src_ids = src_job.result()
        else:     # this thread would only wait: it prepares what the fit asks of the target
            gradient = _prepare_for_fit(target, formulation)
        tgt_names, tgt_ids = tgt_job.result()
    common = [n for n in src_names if n in tgt_names]
    if len(common) < MIN_PAIRS:
        raise ExCloneError(f"only {len(common)} landmarks were found on both faces; "
                           "place the landmarks by hand")
    return (np.array([src_ids[src_names.index(n)] for n in common], dtype=np.int64),
            np.array([tgt_ids[tgt_names.index(n)] for n in common], dtype=np.int64), common,
            gradient)


def _prepare_for_fit(surface, formulation):
    """Has the Surface find the answers the registration and the correspondence ask of a target
    (it keeps them): its outward normals, open borders and areas. Returns its gradient operator
    (deformation.gradient_operator) in the reduced formulation, whose rows for the target region
    the transfer takes (_region_gradient), else None (the 4th-vertex form's unknowns are
    numbered by the region's triangles)."""
    for answer in ("vertex_normals", "triangle_normals", "on_border", "border_search",
                   "vertex_areas", "border_lengths"):
        getattr(surface, answer)
    if formulation != deformation.REDUCED:
        return None
    return deformation.gradient_operator(surface.vertices, surface.triangles, formulation)[0]


def found_landmarks(mesh, what="mesh", face_guide=None):
    """The automatic landmarks of a PolyMesh as a fit finds them: (names, vertex ids in the
    mesh's own numbering); with face_guide, the mesh is a found face's head region (as the fit's
    target). ExCloneError if the face cannot be found."""
    weld = _welded_surface(mesh, what)
    names, ids = _found(weld.surface, face_guide)
    return names, weld.originals[np.asarray(ids, dtype=np.int64)]


def _found(surface, face_guide=None):
    """(names, ids) of the automatic landmarks on a (welded) Surface. With a face_guide (the
    face found in images) the surface is the head region already, the guide's frame is used, and
    its FaceMesh points check the geometric landmarks and stand in for those not found."""
    if face_guide is None:
        region = _where_the_face_is(surface)
        frame = face_frame(region.vertices, region.triangles, region.search)
        return automatic_landmarks(region.vertices, region.triangles, frame, surface=region)
    skin = _skin(surface, face_guide)

    def geometric(nose_tip=None):
        try:
            return automatic_landmarks(surface.vertices, surface.triangles, face_guide.frame,
                                       surface=surface, nose_tip=nose_tip)
        except ExCloneError:      # too few found by geometry: FaceMesh's points stand in
            return [], np.zeros(0, dtype=np.int64)

    names, ids = geometric()
    tip = face_guide.misplaced_nose_tip(names, ids, surface.vertices, skin)
    if tip is not None:           # walked from a wrong tip: found again from FaceMesh's
        names, ids = geometric(tip)
    return face_guide.cross_checked(names, ids, surface.vertices, skin)


def _skin(surface, face_guide):
    """(k,) the vertices of the surface's part nearest to the guide's nose tip (else its
    largest part): where landmarks go, not an eyeball or the teeth."""
    used = surface.used
    tip = face_guide.points.get("nose_tip")
    if tip is None:
        part = np.argmax(np.bincount(surface.parts[used]))
    else:
        part = surface.parts[used[np.argmin(np.linalg.norm(surface.vertices[used] - tip,
                                                            axis=1))]]
    return used[surface.parts[used] == part]


def _where_the_face_is(surface):
    """The Surface the face is looked for on: the connected part of the largest area and the
    parts whose centre lies in its bounding box (eyes, teeth). A loose piece outside it (a stray
    triangle, a prop) would otherwise set the frame's scale, symmetry and nose."""
    labels = surface.parts[surface.triangles[:, 0]]
    areas = np.bincount(labels, triangle_areas(surface.vertices, surface.triangles),
                        minlength=surface.parts.max() + 1)
    used = surface.used
    main = used[surface.parts[used] == np.argmax(areas)]
    low, high = surface.vertices[main].min(axis=0), surface.vertices[main].max(axis=0)
    counts = np.bincount(surface.parts[used], minlength=len(areas))
    centres = np.stack([np.bincount(surface.parts[used], surface.vertices[used, axis],
                                    minlength=len(areas)) for axis in range(3)], axis=1)
    centres /= np.maximum(counts, 1)[:, None]
    inside = np.all((centres >= low) & (centres <= high), axis=1)
    kept = inside[labels]
    return surface if kept.all() else Surface(surface.vertices, surface.triangles[kept])


def _rigid_alignment(source, target, src_lm, tgt_lm, automatic, settings):
    """(R, s, aligned source Surface): the similarity that takes the source into the target's
    frame, from the landmarks. Automatic landmarks are approximate: they start the alignment,
    and the surfaces finish it (a similarity ICP)."""
    rotation, scale, shift = similarity_transform(source.vertices[src_lm], target.vertices[tgt_lm])
    aligned = source.moved(source.vertices @ rotation.T * scale + shift)
    if automatic:
        ids = aligned.used
        r, s, t = similarity_icp(aligned.vertices[ids], aligned.vertex_normals[ids], target,
                                 settings.max_distance * target.diagonal)
        aligned = aligned.moved(aligned.vertices @ r.T * s + t)
        rotation, scale = r @ rotation, s * scale
    return rotation, scale, aligned


def _checked_modes(modes, source_weld):
    """The source's shape modes (k, n_source, 3) in the welded numbering."""
    modes = np.asarray(modes, dtype=np.float64)
    if modes.ndim != 3 or modes.shape[1:] != (source_weld.own_count(), 3):
        raise ExCloneError(f"the source's shape modes have shape {modes.shape}, expected "
                           f"(k, {source_weld.own_count()}, 3)")
    return modes[:, source_weld.originals]


def _shape_start(aligned, target, modes, rotation, scale, settings):
    """(R, s, aligned, start, quality): the similarity and the aligned source refined with the
    source's shape space fitted to the target (modes (k, n, 3) in the welded numbering, the
    source's own frame), and the registration's start, the face of that space nearest the
    target; the aligned source as it was if that face is not plausible (shape_space.plausible).
    The transfer keeps the aligned neutral: the expressions are the source's own. quality: the
    fitted weights' norm and whether the start is that face, for the run's report."""
    r, s, t, weights, face = fit_shape_space(aligned, target, modes @ rotation.T * scale,
                                             settings.max_distance)
    used = plausible(weights)
    quality = {"shape_space_weight_norm": float(np.linalg.norm(weights)),
               "shape_space_start": used}
    if not used:
        return rotation, scale, aligned, aligned, quality
    aligned = aligned.moved(aligned.vertices @ r.T * s + t)
    return r @ rotation, s * scale, aligned, aligned.moved(face), quality


def _registration(aligned, target, src_lm, tgt_lm, automatic, settings, report):
    """The non-rigid registration of the aligned source onto the target region; automatic
    landmarks guide it softly, given ones are hard. ExCloneError if it did not converge."""
    schedule = Schedule.preset(settings.preset)
    schedule.max_distance = settings.max_distance
    if automatic:
        schedule.landmark_weight = settings.landmark_weight
    reg = register(aligned, target, src_lm, target.vertices[tgt_lm],
                   formulation=settings.formulation, schedule=schedule, progress=report)
    if reg.valid_fraction < 0.3:
        raise ExCloneError(
            f"registration did not converge: only {100 * reg.valid_fraction:.0f}% of the source "
            "face found the target surface; check the landmarks")
    return reg


def _correspond(registered, target, settings):
    """Correspondence of the target region with the registered source region (Surfaces): the
    vertex map where plausible, triangle pairs elsewhere. Returns (vertex_map, mapped, pairs,
    weights)."""
    max_distance = settings.max_distance * target.diagonal
    # the source's side of the pairs is found beside the vertex map, which it does not need
    # (numpy and the KD-tree release the GIL)
    with ThreadPoolExecutor(max_workers=1) as pool:
        from_source = pool.submit(source_matches, registered, target, max_distance)
        vertex_map = map_vertices(registered, target, max_distance)
        if settings.correspondence == "vertex":
            mapped = mapped_triangles(vertex_map, registered, target)
        else:
            mapped = np.zeros(len(target.triangles), dtype=bool)
        pairs = triangle_correspondence(registered, target, max_distance, wanted=~mapped,
                                        from_source=from_source.result())
    pairs = pairs.matrix(len(target.triangles), len(registered.triangles))
    weights = np.where(mapped, 1.0, np.asarray(pairs.sum(axis=1)).ravel())
    if not np.any(weights > 0):
        raise ExCloneError("no triangle of the target corresponds to the source; check the landmarks")
    return vertex_map, mapped, pairs, weights


def _registration_quality(reg, diagonal, landmark_count):
    return {"registration_mean_distance": reg.mean_distance,
            "registration_mean_distance_rel": reg.mean_distance / diagonal,
            "registration_valid_fraction": reg.valid_fraction,
            "registration_history_rel": [h / diagonal for h in reg.history],
            "landmark_count": int(landmark_count)}


def _correspondence_quality(mapped, weights, scale, diagonal):
    return {"correspondence_coverage": float(np.mean(weights > 0)),
            "correspondence_vertex_mapped": float(np.mean(mapped)),
            "similarity_scale": scale, "target_diagonal": diagonal}


@limited_threads
def fit_registered(source, target, registered_source, *, settings=None, landmarks=None):
    """A FaceFit from a registration made elsewhere (a known answer, or another tool's wrap of
    the source onto the target): correspondence only, no registration.

    registered_source: (n_source, 3) the source neutral deformed onto the target, in the
    target's coordinates. Every valid triangle of both meshes takes part. The similarity that
    brings the source's expressions into the target's frame is the least-squares one from the
    source to its registered positions.
    landmarks: None, or (names, source ids, target ids) (own numbering), e.g. a clone's: the
    transfer then finds the eyes' lids from them and closes them as a clone does (the eyelid
    rims); without them it has none.
    """
    settings = _checked_settings(settings)
    start = time.perf_counter()
    source_weld, target_weld = _welded_surface(source, "source mesh"), _welded_surface(target, "target mesh")
    source_surface, target_region = source_weld.surface, target_weld.surface
    registered = np.asarray(registered_source, dtype=np.float64)
    expected = (source_weld.own_count(), 3)
    if registered.shape != expected or not np.all(np.isfinite(registered)):
        raise ExCloneError(f"the registered source has shape {registered.shape} or invalid values; "
                           f"expected {expected} finite positions")
    registered_welded = registered[source_weld.originals]
    ids = source_surface.used
    rotation, scale, shift = similarity_transform(source_surface.vertices[ids],
                                                  registered_welded[ids])
    vertex_map, mapped, pairs, weights = _correspond(source_surface.moved(registered_welded),
                                                     target_region, settings)
    names, source_ids, target_ids = landmarks if landmarks is not None else ([], [], [])
    return FaceFit(
        source=source_surface, target=target, welded_target=target_weld, source_weld=source_weld,
        target_region=target_region,
        source_region=source_surface.triangles, rotation=rotation, scale=scale,
        aligned_source=source_surface.vertices @ rotation.T * scale + shift,
        vertex_map=vertex_map, mapped=mapped, pairs=pairs, weights=weights,
        formulation=settings.formulation,
        source_landmarks=np.asarray(source_ids, dtype=np.int64),
        target_landmarks=np.asarray(target_ids, dtype=np.int64),
        landmark_names=list(names), registered_source=registered,
        timings={"correspondence": time.perf_counter() - start},
        quality=_correspondence_quality(mapped, weights, scale, target_region.diagonal))


def _fit_shared(source_weld, target, shared, source_landmarks, settings, fixed_vertices):
    """A FaceFit of a target made from the source's own base mesh (docs/method.md §7; the
    source welded: Welded, whole mesh): each target vertex is a vertex of the source, so nothing
    is registered and each target triangle takes the gradient of its own triangle on the source
    (an ICT-FaceKit head and the bundled library; two characters made from one base mesh).

    shared: (n_target,) the source vertex (own numbering) each target vertex is, -1 where the
    source has none (a triangle with such a corner follows without deforming, as an uncovered
    one). source_landmarks: the source's automatic landmarks (names, ids): those whose vertex
    the target has become the fit's (the eyelid rims and the measures use them).
    fixed_vertices: as fit_faces'."""
    start = time.perf_counter()
    target_weld = _welded_surface(target, "target mesh")
    source_surface, target_region = source_weld.surface, target_weld.surface
    shared = np.asarray(shared, dtype=np.int64)
    if shared.shape != (target_weld.own_count(),) \
            or shared.max(initial=-1) >= source_weld.own_count():
        raise ExCloneError("the shared vertices do not fit the meshes: one source vertex id "
                           f"(or -1) per target vertex, below {source_weld.own_count()}")
    # per welded target vertex, its welded source vertex (-1: none)
    counterpart = np.full(len(target_region.vertices), -1)
    has = shared >= 0
    counterpart[target_weld.index[has]] = source_weld.index[shared[has]]
    vertex_map = _shared_vertex_map(counterpart, source_surface)
    moved = np.flatnonzero(vertex_map.valid)
    at = source_surface.vertices[counterpart[moved]]
    rotation, scale, shift = similarity_transform(at, target_region.vertices[moved])
    aligned = source_surface.vertices @ rotation.T * scale + shift
    registered = aligned.copy()          # the source vertices the target has are where it has them
    registered[counterpart[moved]] = target_region.vertices[moved]
    mapped = vertex_map.valid[target_region.triangles].all(axis=1)
    if not mapped.any():
        raise ExCloneError("the target shares no triangle with the source")
    weights = mapped.astype(np.float64)
    none = np.zeros(0, dtype=np.int64)
    pairs = Correspondence(none, none, np.zeros(0)).matrix(len(target_region.triangles),
                                                          len(source_surface.triangles))
    names, source_ids, target_ids = _shared_landmarks(source_landmarks, shared)
    return FaceFit(
        source=source_surface, target=target, welded_target=target_weld, source_weld=source_weld,
        target_region=target_region, source_region=source_surface.triangles,
        rotation=rotation, scale=scale, aligned_source=aligned,
        vertex_map=vertex_map, mapped=mapped, pairs=pairs, weights=weights,
        formulation=settings.formulation, source_landmarks=source_ids,
        target_landmarks=target_ids, landmark_names=names,
        registered_source=registered[source_weld.index],
        timings={"correspondence": time.perf_counter() - start},
        quality={"shared_vertices": int(has.sum()), "landmark_count": len(names),
                 **_correspondence_quality(mapped, weights, scale, target_region.diagonal)},
        fixed_vertices=_welded_ids(target_weld, fixed_vertices))


def _shared_vertex_map(counterpart, source):
    """correspondence.VertexMap putting each target vertex exactly on its source vertex
    (counterpart, welded ids; -1: none): at a corner of a source triangle holding it."""
    n = len(counterpart)
    triangle, corner = np.full(n, -1), np.zeros(n, dtype=np.int64)
    holder = np.full(len(source.vertices), -1)
    holder_corner = np.zeros(len(source.vertices), dtype=np.int64)
    # any triangle holding the vertex will do: an image's gradient is read at its corners
    for k in range(3):
        holder[source.triangles[:, k]] = np.arange(len(source.triangles))
        holder_corner[source.triangles[:, k]] = k
    valid = counterpart >= 0
    valid[valid] = holder[counterpart[valid]] >= 0
    triangle[valid] = holder[counterpart[valid]]
    corner[valid] = holder_corner[counterpart[valid]]
    bary = np.zeros((n, 3))
    bary[np.flatnonzero(valid), corner[valid]] = 1.0
    return VertexMap(triangle, bary, valid)


def _shared_landmarks(source_landmarks, shared):
    """(names, source ids, target ids) of the source's landmarks whose vertex the target has."""
    if source_landmarks is None:
        return [], np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    names, ids = list(source_landmarks[0]), np.asarray(source_landmarks[1], dtype=np.int64)
    first = {}
    for target_id, source_id in enumerate(shared.tolist()):
        first.setdefault(source_id, target_id)
    kept = [k for k, i in enumerate(ids.tolist()) if i in first]
    return ([names[k] for k in kept], ids[kept],
            np.array([first[int(ids[k])] for k in kept], dtype=np.int64))


# ------------------------------------------------------------------------------ transfer

def _checked_deltas(source_deltas, names, source_weld):
    """The expressions' deltas (E, n_source, 3) as float64 on the welded source (E, k, 3: each
    welded vertex moves as its first copy), checked against the source before any long work:
    ExCloneError naming what is wrong."""
    deltas = np.asarray(source_deltas, dtype=np.float64)
    n_source, source = source_weld.own_count(), source_weld.surface
    if deltas.ndim != 3 or deltas.shape[1:] != (n_source, 3):
        raise ExCloneError(f"expression deltas have shape {deltas.shape}; expected (E, {n_source}, 3)")
    if len(names) != len(deltas):
        raise ExCloneError(f"{len(names)} names for {len(deltas)} expressions")
    broken = ~np.isfinite(deltas).all(axis=(1, 2))
    if broken.any():
        raise ExCloneError(f"source expression(s) {_listed(names, broken)} contain NaN or "
                           "infinite values")
    # A vertex of the face moving further than the whole face measures is no expression: the
    # deltas were made at another scale or in other units than the neutral.
    welded_deltas = deltas[:, source_weld.originals]
    with np.errstate(over="ignore"):
        squared = np.einsum("eij,eij->ei", welded_deltas, welded_deltas)[:, source.used]
    reach = np.sqrt(squared.max(axis=1, initial=0.0))
    absurd = reach > source.diagonal
    if absurd.any():
        raise ExCloneError(
            f"source expression(s) {_listed(names, absurd)} move a vertex by up to "
            f"{reach[absurd].max():.3g}, more than the whole source mesh measures "
            f"({source.diagonal:.3g}): the expressions and the neutral mesh are probably in "
            "different units or scales")
    return welded_deltas


def _listed(names, mask):
    """The names where mask is True, for a message."""
    return listed([name for name, bad in zip(names, mask) if bad], most=5)


@limited_threads
def transfer_expressions(fit, source_deltas, names):
    """Every source expression onto the fitted target: CloneResult (timings and quality include
    the fit's). source_deltas (E, n_source, 3) and the result's deltas (E, n_target, 3) are in
    the meshes' own numbering; every copy of a welded vertex gets its motion. The transfer system
    is factorised once per fit and reused by later calls."""
    start = time.perf_counter()
    deltas = _checked_deltas(source_deltas, names, fit.source_weld)
    # an expression that moves nothing gives exactly nothing (the solve would leave ~1e-16)
    moving = deltas.any(axis=(1, 2))
    if moving.all():
        result = _transferred(fit, deltas)
    else:
        result = np.zeros((len(deltas), len(fit.target_region.vertices), 3))
        if moving.any():
            result[moving] = _transferred(fit, deltas[moving])
    if moving.any():
        _follow_unsolved(result, fit, names)
        _rules_on_solved_parts(result, fit, names)
    timings = dict(fit.timings, transfer=time.perf_counter() - start)
    timings["total"] = sum(timings.values())
    return CloneResult(list(names), _in_own_numbering(result, fit.welded_target.index),
                       fit.source_landmarks, fit.target_landmarks,
                       fit.landmark_names, fit.registered_source, timings, dict(fit.quality),
                       None if fit._rims is None else fit._rims.openings)


def _transferred(fit, deltas):
    """(E, n_target, 3) target displacements of the source expressions' deltas (E, n_source, 3)."""
    if fit._transfer is None:
        system = Transfer(fit.target_region.vertices, fit.target_region.triangles, fit.weights,
                          fit.formulation, fit.fixed_vertices, gradient=fit._gradient)
        fit._transfer = CorrespondedTransfer(system, fit.aligned_source, fit.source_region,
                                             fit.vertex_map, fit.mapped, fit.pairs, fit.weights)
    if fit._rims is None:
        fit._rims = RimGoals(fit.target_region, fit.aligned_source, fit.source_region,
                             fit.source_weld.index[fit.source_landmarks], fit.landmark_names,
                             fit.welded_target.index[fit.target_landmarks], fit.vertex_map,
                             fit._transfer.system)
    result = fit._transfer(deltas @ fit.rotation.T * fit.scale, correction=fit._rims)
    result[:, fit._transfer.fixed] = 0.0       # also where a fixed vertex was left to follow
    if not np.all(np.isfinite(result)):
        raise ExCloneError("transfer produced invalid values (NaN); the target mesh may be broken")
    return result


def _in_own_numbering(result, index):
    """(E, n_own, 3) the welded displacements `result` (E, n, 3) at every own vertex (index:
    each own vertex's welded id); `result` itself where the numberings are the same."""
    if len(index) == result.shape[1] and np.array_equal(index, np.arange(len(index))):
        return result
    own = np.empty((len(result), len(index), 3))
    for expression, welded_motion in zip(own, result):    # one expression at a time: no copy
        expression[:] = welded_motion[index]               # of the whole (E, n, 3) at once
    return own


@limited_threads
def clone_expressions(source, source_deltas, names, target, *, landmarks=None,
                      source_landmarks=None, settings=None, progress=None, face_guide=None,
                      fixed_vertices=None, shared_vertices=None, source_modes=None):
    """Clone every source expression onto the target: fit_faces, then transfer_expressions.

    source, target: PolyMesh. source_deltas: (E, n_source, 3). names: E strings.
    landmarks, source_landmarks, progress, face_guide, fixed_vertices, shared_vertices,
    source_modes: as fit_faces.
    Raises ExCloneError with a user-facing message on bad input.
    """
    settings = _checked_settings(settings)
    source_weld = _welded_surface(source, "source mesh")
    _checked_deltas(source_deltas, names, source_weld)   # before the long part
    fit = _fit(source_weld, target, landmarks, source_landmarks, settings,
               _progress_span(progress, 0.0, 0.8), face_guide, fixed_vertices, shared_vertices,
               source_modes)
    if progress:
        progress(0.8, "transfer")
    result = transfer_expressions(fit, source_deltas, names)
    if progress:
        progress(1.0, "done")
    return result


# ------------------------------------------------------------------------------ unsolved parts

def _follow_unsolved(result, fit, names):
    """Vertices the transfer did not solve (on no triangle of the solved region) follow it
    (docs/method.md §9); result (E, n, 3) in the welded numbering, changed in place.

    In a solved part (only on degenerate, skipped triangles) a vertex copies its nearest solved
    vertex. Separate parts (eyeballs, teeth, lashes) follow by the rules of core/followers.py,
    placed by the fit's landmarks (or the automatic ones of the solved region when the
    landmarks were placed by hand); where no face can be described, they stay still.
    """
    solved_region, all_triangles = fit.target_region, fit.welded_target.mesh.triangles()
    vertices, solved = solved_region.vertices, solved_region.used
    orphans = np.setdiff1d(np.unique(all_triangles), solved)
    if not len(orphans):
        return
    nearest = solved[cKDTree(vertices[solved]).query(vertices[orphans])[1]]
    parts = vertex_parts(len(vertices), all_triangles)
    in_solved_part = np.isin(parts[orphans], parts[solved])
    result[:, orphans[in_solved_part]] = result[:, nearest[in_solved_part]]
    separate = orphans[~in_solved_part]
    face = _face_of(fit) if len(separate) else None
    if face is None:
        return
    triangles = all_triangles[np.isin(all_triangles[:, 0], separate)]
    motion = followers.follow(face, result, names, [(vertices, triangles)])[0].deltas
    result[:, separate] = motion[:, separate]


def _rules_on_solved_parts(result, fit, names):
    """The solved region's separate parts (a target of the source's own base mesh solves them
    all, §7) take what the followers' rules add (§9: eyes turn in eyeLook keys, a tongue comes
    forward in tongueOut); changed in place. The parts not connected to the face's landmarks are
    the separate ones."""
    ruled = [followers.eye_look(name) is not None or name.endswith("tongueOut") for name in names]
    if not len(fit.target_landmarks) or not any(ruled):
        return
    region = fit.target_region
    separate = ~np.isin(region.parts, region.parts[fit.welded_target.index[fit.target_landmarks]])
    triangles = region.triangles[separate[region.triangles[:, 0]]]
    face = _face_of(fit) if len(triangles) else None
    if face is not None:
        result += followers.on_solved_parts(face, result, names, region.vertices, triangles)


def _face_of(fit):
    """followers.Face of the fit's solved region, from its landmarks' names and positions, or
    its automatic landmarks; None if neither describes a face."""
    region = fit.target_region
    points = dict(zip(fit.landmark_names,
                      region.vertices[fit.welded_target.index[fit.target_landmarks]]))
    try:
        if not set(followers.FACE_POINTS) <= set(points):
            names, ids = _found(region)
            points = dict(zip(names, region.vertices[np.asarray(ids, dtype=np.int64)]))
        return followers.face_from_points(region.vertices, region.triangles, points)
    except ExCloneError:
        return None


# ------------------------------------------------------------------------------ plumbing

class _Stopwatch:
    """Seconds per phase: lap(name) records the time since the previous lap."""

    def __init__(self):
        self.timings = {}
        self._clock = time.perf_counter()

    def lap(self, name):
        now = time.perf_counter()
        self.timings[name] = now - self._clock
        self._clock = now


def _progress_span(progress, start, end):
    """progress(fraction, message) for a phase that runs from `start` to `end` of the whole
    (a no-op without a progress callable)."""
    def report(fraction, message):
        if progress:
            progress(start + (end - start) * fraction, message)
    return report
