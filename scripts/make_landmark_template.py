"""Write exclone_addon/data/landmark_template.json: the bundled face's landmarks as the template
that places the non-heuristic landmarks on other faces (core.landmarks), and the bundled library's
own automatic landmarks (vertex ids), so a clone from the library only looks for the target's.
Run it after changing the landmark heuristics or the bundled library;
blender_tests/test_landmarks.py checks it is current.

    .venv/bin/python scripts/make_landmark_template.py
"""
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from exclone_addon.core.data import LANDMARK_TEMPLATE_FILE as TEMPLATE_FILE  # noqa: E402
from exclone_addon.core.landmark_template import compute_template  # noqa: E402


def main():
    template, normals, (names, ids) = compute_template()
    data = {
        "about": "canonical positions (+X left, +Y up, +Z forward; library units) of the bundled "
                 "ICT-FaceKit face's landmarks, the outward normals of those placed by their "
                 "normal, and its automatic landmarks as vertex ids; made by "
                 "scripts/make_landmark_template.py",
        "canonical_positions": {name: [round(float(c), 9) for c in p] for name, p in template.items()},
        "canonical_normals": {name: [round(float(c), 9) for c in n] for name, n in normals.items()},
        "library_landmarks": {name: int(i) for name, i in zip(names, ids)},
    }
    TEMPLATE_FILE.write_text(json.dumps(data, indent=1) + "\n")
    print(f"make_landmark_template: wrote {len(template)} landmarks to {TEMPLATE_FILE}")


if __name__ == "__main__":
    main()
