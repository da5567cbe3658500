"""The files ExClone ships: where each one lives and how it is read (the one owner of these paths).

data/   the expression library, the demo head, MediaPipe's canonical face, and the files derived
        from them at build time (the landmark template, the tracker model, the appearance map);
        licences beside them.
models/ the face detector and landmark models, extracted from the mediapipe wheel by setup.
"""
import json
from functools import lru_cache
from pathlib import Path

import numpy as np

from .errors import ExCloneError
from .mesh import read_obj

PACKAGE_DIR = Path(__file__).resolve().parent.parent
DATA_DIR = PACKAGE_DIR / "data"
MODELS_DIR = PACKAGE_DIR / "models"

LIBRARY_FILE = DATA_DIR / "ict_arkit_library.npz"
DEMO_HEAD_FILE = DATA_DIR / "demo_head.obj"
CANONICAL_FACE_FILE = DATA_DIR / "canonical_face.obj"
LANDMARK_TEMPLATE_FILE = DATA_DIR / "landmark_template.json"
TRACKER_MODEL_FILE = DATA_DIR / "tracker_model.npz"
APPEARANCE_MAP_FILE = DATA_DIR / "appearance_map.npz"


def _shipped(path, remedy):
    if not path.is_file():
        raise ExCloneError(f"bundled file {path} is missing; {remedy}")
    return path


@lru_cache(maxsize=1)
def landmark_template():
    """The landmark template as shipped (scripts/make_landmark_template.py writes it):
    canonical_positions, canonical_normals and library_landmarks, each {name: value}."""
    path = _shipped(LANDMARK_TEMPLATE_FILE, "run scripts/make_landmark_template.py")
    return json.loads(path.read_text())


def versioned_arrays(path, version, what, remedy):
    """The arrays (a dict) of a file derived at build time, written with `format_version`
    `version`; a missing file or another version is an ExCloneError naming `what` and the
    `remedy`."""
    path = Path(path)
    if not path.is_file():
        raise ExCloneError(f"{what} {path} is missing; {remedy}")
    with np.load(path, allow_pickle=False) as stored:
        if int(stored["format_version"]) != version:
            raise ExCloneError(f"{what} {path} has an old format; {remedy}")
        return dict(stored)


def demo_head():
    """The bundled demo head (MakeHuman, CC0) as a PolyMesh."""
    return read_obj(_shipped(DEMO_HEAD_FILE, "reinstall ExClone"))


def canonical_face():
    """MediaPipe's canonical face (468 vertices, FaceMesh's landmark order) as a PolyMesh."""
    return read_obj(_shipped(CANONICAL_FACE_FILE, "reinstall ExClone"))
