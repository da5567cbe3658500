"""The whole cloning pipeline: landmarks -> registration -> correspondence -> transfer.

(Interface fixed first so the Blender layer and the batch script can be written against it; the
engine behind it lands in the following commits.)
"""
from dataclasses import dataclass, field

import numpy as np

from .mesh import PolyMesh


@dataclass
class CloneSettings:
    preset: str = "balanced"          # "fast" | "balanced" | "precise": registration schedule
    formulation: str = "reduced"      # "reduced" (2-edge QR gradient) | "augmented" (4th vertex)


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


def clone_expressions(source, source_deltas, names, target, *, landmarks=None, settings=None,
                      progress=None):
    """Clone every source expression onto the target.

    source, target: PolyMesh. source_deltas: (E, n_source, 3). names: E strings.
    landmarks: None for automatic ones, or {"source": ids, "target": ids} (same length).
    progress: optional callable(fraction, message); it may raise core.errors.Cancelled.
    Raises ExCloneError with a user-facing message on bad input.
    """
    raise NotImplementedError("cloning engine not implemented yet")
