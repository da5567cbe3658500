"""Expression libraries: a neutral source mesh plus named per-vertex deltas.

Sources: the bundled ICT-FaceKit ARKit library (data/ict_arkit_library.npz, made by
scripts/make_library.py) or a folder of OBJs (neutral.obj + one OBJ per expression).
"""
import zipfile
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from . import data
from .errors import ExCloneError
from .followers import TONGUE_OUT_JAW_OPEN
from .mesh import PolyMesh, read_obj

SUPPORTED_FORMAT = 1

# Apple's 52 ARKit blend shapes as the raw string values of ARFaceAnchor.BlendShapeLocation, in
# the order of Apple's list. The Swift constants are spelled eyeBlinkLeft etc., but their raw
# values (what ARKit reports and what ICT-FaceKit uses) are "eyeBlink_L" etc. Sources: Apple,
# developer.apple.com/documentation/arkit/arfaceanchor/blendshapelocation (the 52 constants), and
# printed ARKit output such as `BlendShapeLocation(rawValue: "eyeBlink_L")` for the raw values.
ARKIT_BLENDSHAPES = [
    "browInnerUp", "browDown_L", "browDown_R", "browOuterUp_L", "browOuterUp_R",
    "eyeLookUp_L", "eyeLookUp_R", "eyeLookDown_L", "eyeLookDown_R", "eyeLookIn_L", "eyeLookIn_R",
    "eyeLookOut_L", "eyeLookOut_R", "eyeBlink_L", "eyeBlink_R", "eyeSquint_L", "eyeSquint_R",
    "eyeWide_L", "eyeWide_R", "cheekPuff", "cheekSquint_L", "cheekSquint_R", "noseSneer_L",
    "noseSneer_R", "jawOpen", "jawForward", "jawLeft", "jawRight", "mouthFunnel", "mouthPucker",
    "mouthLeft", "mouthRight", "mouthRollUpper", "mouthRollLower", "mouthShrugUpper",
    "mouthShrugLower", "mouthClose", "mouthSmile_L", "mouthSmile_R", "mouthFrown_L", "mouthFrown_R",
    "mouthDimple_L", "mouthDimple_R", "mouthUpperUp_L", "mouthUpperUp_R", "mouthLowerDown_L",
    "mouthLowerDown_R", "mouthPress_L", "mouthPress_R", "mouthStretch_L", "mouthStretch_R",
    "tongueOut",
]
# ARKit shapes that ICT-FaceKit splits into a left and a right half.
ARKIT_SPLIT = {"browInnerUp": ("browInnerUp_L", "browInnerUp_R"),
               "cheekPuff": ("cheekPuff_L", "cheekPuff_R")}


@dataclass
class ExpressionLibrary:
    mesh: PolyMesh              # the neutral source mesh
    names: list                 # E expression names
    deltas: np.ndarray          # (E, n, 3) float64: expression e = neutral + deltas[e]
    landmarks68: np.ndarray = None                   # (68,) vertex ids, iBUG order, or None
    parts: dict = field(default_factory=dict)        # name -> (start, stop) vertex range
    # its automatic landmarks found once, (names, vertex ids): shipped for the bundled library
    automatic_landmarks: tuple = None
    description: str = ""      # what it is, for reports: "the built-in ARKit library", a path
    # the head region of a bigger mesh (a full body) the library was cut to, as a
    # core.character.HeadCut (its ids: the mesh object's own numbering), or None: used whole
    head: object = None
    # (k, n, 3) how the neutral varies between faces (the bundled library: the ICT identity
    # model's first modes, over its face part), or None: the registration starts from the face
    # of that space nearest the target (core.shape_space)
    shape_modes: np.ndarray = None

    @property
    def own_vertex_count(self):
        """Vertices of the mesh object the library was read from (a cut body's whole count)."""
        return len(self.mesh.vertices) if self.head is None else self.head.total

    def ids_from_own(self, ids):
        """The mesh object's own vertex ids `ids` in the library's numbering (its head region's
        when it was cut to one), or None if any lies outside that region."""
        return np.asarray(ids, dtype=np.int64) if self.head is None else self.head.head_ids(ids)

    def own_ids(self, ids):
        """The library's vertex ids `ids` in the numbering of the mesh object it was read from."""
        return np.asarray(ids, dtype=np.int64) if self.head is None else self.head.own_ids(ids)

    def subset(self, names):
        """The library restricted to `names`, in that order."""
        index = {name: i for i, name in enumerate(self.names)}
        unknown = [name for name in names if name not in index]
        if unknown:
            raise ExCloneError(f"unknown expression(s) {', '.join(unknown)}; "
                               f"available: {', '.join(self.names)}")
        rows = [index[name] for name in names]
        return replace(self, names=list(names), deltas=self.deltas[rows], parts=dict(self.parts))

    def with_tongue_out(self):
        """The library with a tongueOut of its own where it has jawOpen and no tongueOut
        (tongue_out_of_jaw), so that a clone makes it on every part of the target: a one-mesh
        head's own tongue comes forward in it as a separate tongue object's does."""
        if "tongueOut" in self.names or "jawOpen" not in self.names:
            return self
        jaw = self.deltas[self.names.index("jawOpen")]
        return replace(self, names=self.names + ["tongueOut"],
                       deltas=np.concatenate([self.deltas, tongue_out_of_jaw(jaw)[None]]),
                       parts=dict(self.parts))


def tongue_out_of_jaw(jaw_open):
    """A tongueOut for a face without one, from its jawOpen deltas (..., 3): the jaw opened by
    followers.TONGUE_OUT_JAW_OPEN (Apple's reference shape shows the mouth half open); the
    followers bring the tongue forward in it (a face without a tongue still opens its mouth, as a
    performer's does)."""
    return TONGUE_OUT_JAW_OPEN * np.asarray(jaw_open)


def load_library(path=None):
    """Load an expression library .npz (default: the bundled ICT-FaceKit ARKit library)."""
    path = Path(path) if path is not None else data.LIBRARY_FILE
    if not path.is_file():
        raise ExCloneError(f"expression library not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as archive:
            version = int(archive["format_version"])
            if version != SUPPORTED_FORMAT:
                raise ExCloneError(f"expression library {path} has format {version}, "
                                   f"this ExClone reads format {SUPPORTED_FORMAT}")
            vertices = archive["vertices"].astype(np.float64)
            loop_totals = archive["loop_totals"].astype(np.int64)
            loop_vertices = archive["loop_vertices"].astype(np.int64)
            names = [str(name) for name in archive["names"]]
            moving = np.unpackbits(archive["delta_mask"], axis=1, count=len(vertices)).astype(bool)
            values = archive["delta_values"].astype(np.float64)
            landmarks = archive["landmarks68"].astype(np.int64)
            parts = {str(name): (int(start), int(stop))
                     for name, (start, stop) in zip(archive["part_names"], archive["part_ranges"])}
            # optional: over the first vertices (the face part); the others do not vary
            kept_modes = (archive["identity_modes"].astype(np.float64)
                          if "identity_modes" in archive.files else None)
    except ExCloneError:
        raise
    except (OSError, ValueError, KeyError, TypeError, zipfile.BadZipFile, EOFError) as exc:
        raise ExCloneError(f"expression library {path} is unreadable or corrupt ({exc})") from exc
    n = len(vertices)
    consistent = (vertices.ndim == 2 and vertices.shape[1] == 3
                  and loop_totals.sum() == len(loop_vertices)
                  and (len(loop_vertices) == 0 or 0 <= loop_vertices.min() <= loop_vertices.max() < n)
                  and moving.shape == (len(names), n) and values.shape == (moving.sum(), 3)
                  and (len(landmarks) == 0 or 0 <= landmarks.min() <= landmarks.max() < n)
                  and (kept_modes is None or (kept_modes.ndim == 3 and kept_modes.shape[1] <= n
                                              and kept_modes.shape[2] == 3)))
    if not consistent:
        raise ExCloneError(f"expression library {path} is corrupt (inconsistent array sizes)")
    deltas = np.zeros((len(names), n, 3))
    deltas[moving] = values
    shape_modes = None
    if kept_modes is not None:
        shape_modes = np.zeros((len(kept_modes), n, 3))
        shape_modes[:, :kept_modes.shape[1]] = kept_modes
    bundled = path.resolve() == data.LIBRARY_FILE.resolve()
    return ExpressionLibrary(PolyMesh(vertices, loop_totals, loop_vertices), names, deltas,
                             landmarks if len(landmarks) else None, parts,
                             library_landmarks() if bundled else None,
                             "the built-in ARKit library" if bundled else str(path),
                             shape_modes=shape_modes)


def library_landmarks():
    """The bundled library's automatic landmarks as shipped with the template: (names, vertex
    ids); None before scripts/make_landmark_template.py first wrote them."""
    marks = data.landmark_template().get("library_landmarks")
    if marks is None:
        return None
    return list(marks), np.array(list(marks.values()), dtype=np.int64)


def load_obj_folder(folder):
    """A library from `folder`: neutral.obj plus one OBJ per expression (name = file stem)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ExCloneError(f"expression folder not found: {folder}")
    neutral_path = folder / "neutral.obj"
    if not neutral_path.is_file():
        raise ExCloneError(f"expression folder {folder} has no neutral.obj")
    paths = sorted(p for p in folder.iterdir()
                   if p.suffix.lower() == ".obj" and p.name != "neutral.obj" and p.is_file())
    if not paths:
        raise ExCloneError(f"expression folder {folder} has neutral.obj but no expression OBJs")
    neutral = read_obj(neutral_path)
    n = len(neutral.vertices)
    deltas = np.empty((len(paths), n, 3))
    for i, path in enumerate(paths):
        # an expression's polygons are the neutral's: only its vertices are read
        vertices = read_obj(path, faces=False).vertices
        if len(vertices) != n:
            raise ExCloneError(f"{path.name} has {len(vertices)} vertices but neutral.obj has {n}; "
                               "every expression OBJ must have the neutral's vertices in its order")
        deltas[i] = vertices - neutral.vertices
    return ExpressionLibrary(neutral, [p.stem for p in paths], deltas, description=str(folder))


def arkit_blendshapes(names, deltas):
    """Rename/combine expressions to Apple's ARKit set.

    Returns (arkit_names, arkit_deltas, missing): the ARKit shapes available, in Apple's order
    (split _L/_R halves of browInnerUp and cheekPuff are summed into one shape; non-ARKit
    expressions are dropped), and the ARKit names that could not be made. Without its own
    tongueOut, tongueOut is tongue_out_of_jaw of jawOpen.
    """
    index = {name: i for i, name in enumerate(names)}
    out_names, out_deltas, missing = [], [], []
    for name in ARKIT_BLENDSHAPES:
        halves = ARKIT_SPLIT.get(name, ())
        if name in index:
            out_deltas.append(deltas[index[name]])
        elif halves and all(h in index for h in halves):
            out_deltas.append(sum(deltas[index[h]] for h in halves))
        elif name == "tongueOut" and "jawOpen" in index:
            out_deltas.append(tongue_out_of_jaw(deltas[index["jawOpen"]]))
        else:
            missing.append(name)
            continue
        out_names.append(name)
    shape = (0,) + tuple(np.shape(deltas)[1:])
    stacked = np.stack(out_deltas) if out_deltas else np.zeros(shape)
    return out_names, stacked, missing
