"""pytest setup shared by both halves of the suite; it never imports bpy.

core/     the pure numpy/scipy/OpenCV core: runs without bpy (scripts/test.sh proves it by
          running this half with bpy made unimportable).
blender/  the Blender layer and the command lines, in background Blender (the pip `bpy` module).
helpers/  builders the tests share (known-answer meshes and takes, a stand-in UI layout).
"""
import sys
from pathlib import Path

import pytest

sys.dont_write_bytecode = True  # tests must not write into the repo
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # exclone_addon, blender_tests

from blender_tests.helpers.paths import SHARED_DATA  # noqa: E402


@pytest.fixture(scope="session")
def shared_data():
    """Path to the shared real data (../shared/data next to the repo); skips the test where absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not found at {SHARED_DATA}; this test needs the ICT-FaceKit/MakeHuman meshes")
    return SHARED_DATA
