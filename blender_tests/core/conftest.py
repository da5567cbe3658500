"""The pure core's tests. With EXCLONE_WITHOUT_BPY=1 (as scripts/test.sh runs them) any import of
bpy fails, so a core test or module that needs Blender is caught."""
import importlib.abc
import os
import sys


class _NoBpy(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "bpy" or name.startswith(("bpy.", "bpy_extras", "mathutils")):
            raise ImportError(f"the core tests must run without Blender, but {name} was imported")
        return None


if os.environ.get("EXCLONE_WITHOUT_BPY"):
    sys.modules.pop("bpy", None)
    sys.meta_path.insert(0, _NoBpy())
