"""Copy the three face models (detector, FaceMesh, iris) and the licence out of a mediapipe wheel (a zip) into a folder.

Usage: python scripts/extract_models.py MEDIAPIPE.whl OUT_DIR
"""
import sys
import zipfile
from pathlib import Path

MODELS = {
    "mediapipe/modules/face_detection/face_detection_short_range.tflite",
    "mediapipe/modules/face_landmark/face_landmark.tflite",
    "mediapipe/modules/iris_landmark/iris_landmark.tflite",
}


def main(wheel, out_dir):
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(wheel) as zf:
        names = set(zf.namelist())
        missing = MODELS - names
        if missing:
            sys.exit(f"extract_models: {wheel} lacks {sorted(missing)}")
        for name in MODELS:
            (out / Path(name).name).write_bytes(zf.read(name))
        licence = next((n for n in names if n.endswith(".dist-info/LICENSE")), None)
        if licence:
            (out / "LICENSE-mediapipe-Apache-2.0.txt").write_bytes(zf.read(licence))
    print(f"extract_models: wrote {', '.join(sorted(Path(n).name for n in MODELS))} to {out}")


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__.strip())
    main(sys.argv[1], sys.argv[2])
