"""Clone facial expressions onto a head from the command line (see exclone_addon/batch.py).

    python scripts/batch_clone.py [--source S] [--target T] [--out OUT.blend] [--export-dir DIR]
        [--report R.json] [--landmarks L.json] [--shapes NAME,NAME...] [--preview P.png]
    python scripts/batch_clone.py --target T1 --target T2|FOLDER ... [--out-dir DIR] [--jobs N]
    blender -b --python scripts/batch_clone.py -- ARGS

With no arguments: the bundled ICT-FaceKit ARKit library onto the bundled demo head, written to
out/demo_head_exclone.blend, .json and .png.

Several targets (--target given more than once, or a folder of meshes) make a batch: each target
runs in its own process, --jobs N at a time, writing <out-dir>/<target>_exclone.blend, .json and
.png, plus one summary report (--report, default <out-dir>/batch_report.json). A bad target is
reported and skipped; the exit code is non-zero if any target failed.
"""
import sys
from pathlib import Path

import bpy

try:
    import scipy  # noqa: F401  (Blender ships numpy but not scipy)
except ImportError:
    sys.exit("batch_clone: error: scipy is not available in this Python; inside Blender, install and "
             "enable the ExClone extension first (it bundles scipy), or run with .venv/bin/python")

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from exclone_addon.batch import main  # noqa: E402  (needs the repository on sys.path)


def script_arguments():
    if "--" in sys.argv:
        return sys.argv[sys.argv.index("--") + 1:]
    # Inside the Blender executable, sys.argv holds Blender's own options.
    return [] if bpy.app.binary_path else sys.argv[1:]


if __name__ == "__main__":
    sys.exit(main(script_arguments()))
