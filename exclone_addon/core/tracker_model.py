"""The tracker's 3D shape model: the file that ships it (build and read) and the model built from it.

The model is MediaPipe's canonical face (468 points, FaceMesh's order) with the bundled ICT
library's expressions sampled where those points lie on ICT's skin (docs/method.md §11). Finding
them there is a registration (about 5 s); its result, a surface location per point, ships in
data/tracker_model.npz (written by scripts/make_tracker_model.py), so loading the model costs
reading the library and a small PCA (about 0.4 s, once per process).
"""
import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import data
from .errors import ExCloneError
from .library import load_library
from .retarget import SurfaceLocations, locate_canonical_face
from .tracking import ShapeModel, expression_shape_model

TRACKER_MODEL_VERSION = 1
REMEDY = "run scripts/make_tracker_model.py"


# -- build time -------------------------------------------------------------------------------------

def locate_tracker_landmarks(library=None, progress=None):
    """Where the canonical face's 468 points lie on the bundled ICT face's skin (a registration)."""
    library = library or load_library()
    triangles = library.mesh.triangles()
    start, stop = library.parts["face"]      # ICT's skin, as its README defines it
    skin = triangles[np.all((triangles >= start) & (triangles < stop), axis=1)]
    locations, _ = locate_canonical_face(data.canonical_face(), library.mesh, skin,
                                         progress=progress)
    return locations


def write_tracker_model(locations, path=data.TRACKER_MODEL_FILE):
    np.savez_compressed(path, format_version=np.int64(TRACKER_MODEL_VERSION),
                        library=np.str_(data.LIBRARY_FILE.name),
                        corners=locations.corners.astype(np.int32), bary=locations.bary)


# -- run time ---------------------------------------------------------------------------------------

def read_tracker_locations(path=data.TRACKER_MODEL_FILE):
    """The shipped surface locations of the canonical face's points on the library's face."""
    path = Path(path)
    if not path.is_file():
        raise ExCloneError(f"tracker model {path} is missing; {REMEDY}")
    with np.load(path, allow_pickle=False) as stored:
        if int(stored["format_version"]) != TRACKER_MODEL_VERSION:
            raise ExCloneError(f"tracker model {path} has an old format; {REMEDY}")
        return SurfaceLocations(stored["corners"].astype(np.int64),
                                stored["bary"].astype(np.float64))


@dataclass(frozen=True)
class TrackerModel:
    """The tracker's 3D shape model (canonical face + ICT expression modes) in the canonical
    face's units (cm) and axes."""
    shape_model: ShapeModel
    canonical: np.ndarray      # (468, 3) MediaPipe's canonical face

    @classmethod
    def from_locations(cls, locations, library=None):
        library = library or load_library()
        canonical = data.canonical_face()
        model = expression_shape_model(canonical.vertices, locations.sample(library.mesh.vertices),
                                       locations.sample(library.deltas),
                                       triangles=canonical.triangles())
        return cls(model, canonical.vertices)


@functools.lru_cache(maxsize=1)
def load_tracker_model():
    """The bundled tracker model, built once per process from data/tracker_model.npz."""
    return TrackerModel.from_locations(read_tracker_locations())
