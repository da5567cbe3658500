"""Build ExClone's bundled data from the shared real data.

Usage: python scripts/make_library.py [SHARED_DATA_DIR]   (default: ../shared/data from the repo root)

Writes into exclone_addon/data/:
  ict_arkit_library.npz  ICT-FaceKit neutral head + 57 expressions (sparse float32 deltas), 68
                         landmark vertex ids (iBUG order), the named part vertex ranges and the
                         ICT identity model's first 30 modes over the face part (float16)
  demo_head.obj          MakeHuman head neutral.obj, byte-for-byte copy (the demo target)
  canonical_face.obj     MediaPipe canonical face, byte-for-byte copy (vertex i = landmark i)
  LICENSE-*              the licences of the three sources
The output is deterministic: same input, same bytes.
"""
import json
import shutil
import sys
import zipfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from exclone_addon.core.mesh import read_obj  # noqa: E402

OUT = REPO / "exclone_addon" / "data"
LIBRARY_NAME = "ict_arkit_library.npz"
FORMAT_VERSION = 1
N_ICT_VERTICES = 26719
# Below this a vertex counts as not moving; dropping such deltas bounds the round-trip error.
MOVE_THRESHOLD = 1e-6
# float16 deltas are only acceptable if they keep the error below this (centimetres).
FLOAT16_TOLERANCE = 1e-4
# The identity modes are kept over the face part only (the registration's region); float16 keeps
# them within this (centimetres): they only start the registration.
IDENTITY_TOLERANCE = 1e-2
# Part vertex ranges from the ICT-FaceKit README, as [start, stop).
ICT_PARTS = [
    ("face", 0, 9409),
    ("head_and_neck", 9409, 11248),
    ("mouth_socket", 11248, 13294),
    ("eye_sockets", 13294, 14062),
    ("gums_and_tongue", 14062, 17039),
    ("teeth", 17039, 21451),
    ("eyeballs", 21451, 24591),
    ("eye_blend_occlusion", 24591, 25351),
    ("eyelashes", 25351, 26719),
]
COPIES = [
    ("makehuman-head/neutral.obj", "demo_head.obj"),
    ("mediapipe-canonical-face/canonical_face_model.obj", "canonical_face.obj"),
    ("ict-facekit/LICENSE", "LICENSE-ICT-FaceKit.txt"),
    ("makehuman-head/LICENSE.ASSETS.md", "LICENSE-MakeHuman-CC0.md"),
    ("mediapipe-canonical-face/LICENSE_mediapipe_Apache-2.0.txt", "LICENSE-MediaPipe-Apache-2.0.txt"),
]


def fail(message):
    sys.exit(f"make_library: {message}")


def save_npz_deterministic(path, arrays):
    """np.savez_compressed, but with fixed zip timestamps so the bytes only depend on the data."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=9) as zf:
        for key, value in arrays.items():
            info = zipfile.ZipInfo(key + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            with zf.open(info, "w", force_zip64=True) as fh:
                np.lib.format.write_array(fh, np.asanyarray(value), allow_pickle=False)


def build_library(ict):
    mesh = read_obj(ict / "neutral.obj")
    if len(mesh.vertices) != N_ICT_VERTICES:
        fail(f"{ict / 'neutral.obj'} has {len(mesh.vertices)} vertices, expected {N_ICT_VERTICES}")
    with np.load(ict / "expressions.npz") as data:
        names = [str(n) for n in data["names"]]
        deltas = data["deltas"]
    if deltas.shape != (len(names), N_ICT_VERTICES, 3):
        fail(f"expressions.npz deltas have shape {deltas.shape}, expected ({len(names)}, {N_ICT_VERTICES}, 3)")
    landmarks = np.array(json.loads((ict / "landmarks68.json").read_text())["multipie68_vertex_ids"])
    if landmarks.shape != (68,) or landmarks.min() < 0 or landmarks.max() >= N_ICT_VERTICES:
        fail("landmarks68.json must hold 68 vertex ids of the ICT mesh")

    moving = np.abs(deltas).max(axis=2) > MOVE_THRESHOLD       # (E, n)
    values = deltas[moving]                                     # (k, 3), expression-major order
    as_half = values.astype(np.float16).astype(np.float32)
    half_error = float(np.abs(as_half - values).max())
    use_half = half_error < FLOAT16_TOLERANCE
    print(f"float16 deltas: max abs error {half_error:.3g} cm "
          f"({'used' if use_half else 'rejected'}, tolerance {FLOAT16_TOLERANCE:g} cm)")
    arrays = {
        "format_version": np.array(FORMAT_VERSION, dtype=np.int32),
        "vertices": mesh.vertices.astype(np.float32),
        "loop_totals": mesh.loop_totals.astype(np.int32),
        "loop_vertices": mesh.loop_vertices.astype(np.int32),
        "names": np.array(names),
        # moving[e, v] packed to bits; delta_values lists the moving vertices' deltas in that order
        "delta_mask": np.packbits(moving, axis=1),
        "delta_values": values.astype(np.float16 if use_half else np.float32),
        "landmarks68": landmarks.astype(np.int32),
        "part_names": np.array([p[0] for p in ICT_PARTS]),
        "part_ranges": np.array([p[1:] for p in ICT_PARTS], dtype=np.int32),
        "identity_modes": identity_modes(ict),
    }
    out = OUT / LIBRARY_NAME
    save_npz_deterministic(out, arrays)
    return out, mesh, names, deltas


def identity_modes(ict):
    """The identity model's modes over the face part, float16 (k, face vertices, 3)."""
    with np.load(ict / "identities.npz") as data:
        modes = data["deltas"]
    if modes.ndim != 3 or modes.shape[1:] != (N_ICT_VERTICES, 3):
        fail(f"identities.npz deltas have shape {modes.shape}, expected (k, {N_ICT_VERTICES}, 3)")
    face_stop = dict((name, stop) for name, _, stop in ICT_PARTS)["face"]
    kept = modes[:, :face_stop]
    error = float(np.abs(kept.astype(np.float16).astype(np.float32) - kept).max())
    if error > IDENTITY_TOLERANCE:
        fail(f"float16 identity modes err {error:.3g} cm (tolerance {IDENTITY_TOLERANCE:g} cm)")
    print(f"identity modes: {len(kept)} over {face_stop} vertices, float16 max abs error "
          f"{error:.3g} cm")
    return kept.astype(np.float16)


def check_round_trip(path, mesh, names, deltas):
    from exclone_addon.core.library import load_library

    lib = load_library(path)
    if lib.names != names or not np.array_equal(lib.mesh.loop_vertices, mesh.loop_vertices) \
            or not np.array_equal(lib.mesh.loop_totals, mesh.loop_totals):
        fail("round trip changed the names or the polygons")
    delta_error = float(np.abs(lib.deltas - deltas).max())
    vertex_error = float(np.abs(lib.mesh.vertices - mesh.vertices).max())
    print(f"round trip: max abs delta error {delta_error:.3g} cm, "
          f"max abs vertex error {vertex_error:.3g} cm (float32 vs neutral.obj)")


def main(shared):
    shared = Path(shared).resolve()
    if not (shared / "ict-facekit").is_dir():
        fail(f"{shared} has no ict-facekit folder (pass the shared data folder)")
    OUT.mkdir(parents=True, exist_ok=True)
    out, mesh, names, deltas = build_library(shared / "ict-facekit")
    for src, dst in COPIES:
        shutil.copyfile(shared / src, OUT / dst)
    check_round_trip(out, mesh, names, deltas)
    for path in [out] + [OUT / dst for _, dst in COPIES]:
        print(f"{path.relative_to(REPO)}: {path.stat().st_size / 1e6:.2f} MB")


if __name__ == "__main__":
    if len(sys.argv) > 2:
        sys.exit(__doc__.strip())
    main(sys.argv[1] if len(sys.argv) == 2 else REPO.parent / "shared" / "data")
