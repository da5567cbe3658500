"""The Blender layer's tests run in background Blender through the pip `bpy` module.

The add-on is registered once per session; every test starts from a factory-empty scene.
"""
import os
import shutil
import tempfile

import pytest

# Blender's user config, scripts and extensions go to a temporary directory, never the real user's.
BLENDER_USER_RESOURCES = tempfile.mkdtemp(prefix="exclone-blender-user-")
os.environ["BLENDER_USER_RESOURCES"] = BLENDER_USER_RESOURCES

import bpy  # noqa: E402  (after BLENDER_USER_RESOURCES is set)

import exclone_addon  # noqa: E402


def pytest_unconfigure(config):
    shutil.rmtree(BLENDER_USER_RESOURCES, ignore_errors=True)
@pytest.fixture(scope="session")
def exclone_operators():
    """Registers the add-on for the whole session; yields the names of its bpy.ops.exclone operators."""
    if not hasattr(exclone_addon, "register"):
        pytest.fail("exclone_addon has no register(): exclone_addon/__init__.py must register the add-on")
    exclone_addon.register()
    operators = set(dir(bpy.ops.exclone))
    if not operators:
        pytest.fail("exclone_addon.register() registered no bpy.ops.exclone operators")
    yield operators
    exclone_addon.unregister()


@pytest.fixture(autouse=True)
def factory_empty_scene(exclone_operators):
    """A fresh factory-empty scene for every test, with the add-on still registered."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    # The reset also resets preferences and add-ons; classes registered by hand survive it, and
    # the tests would silently stop testing the add-on if a Blender update changed that.
    lost = exclone_operators - set(dir(bpy.ops.exclone))
    assert not lost, f"read_factory_settings unregistered bpy.ops.exclone.{', '.join(sorted(lost))}"
    yield bpy.context.scene


