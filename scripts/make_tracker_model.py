"""Write exclone_addon/data/tracker_model.npz: where the canonical face's 468 points lie on the
bundled ICT-FaceKit face (a registration, about 5 s), from which core.tracker_model builds the
tracker's shape model in well under a second. Run it after changing the bundled library, the
canonical face or the cloning engine; blender_tests/core/test_live.py checks it is current.

    .venv/bin/python scripts/make_tracker_model.py
"""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from exclone_addon.core.data import TRACKER_MODEL_FILE  # noqa: E402
from exclone_addon.core.tracker_model import (locate_tracker_landmarks,  # noqa: E402
                                              write_tracker_model)


def main():
    locations = locate_tracker_landmarks()
    write_tracker_model(locations)
    print(f"make_tracker_model: wrote {len(locations.corners)} surface locations to {TRACKER_MODEL_FILE}")


if __name__ == "__main__":
    main()
