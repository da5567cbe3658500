"""Where the tests find the repository, their fixtures and the shared real data."""
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
FIXTURES = REPO_ROOT / "blender_tests" / "fixtures"
# Real meshes too big for the repository (ICT-FaceKit, MakeHuman characters): tests that need
# them skip where this folder is absent.
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"
