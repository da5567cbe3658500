"""ExClone: clone facial expressions (shape keys) from one head mesh onto another.

A Blender 4.2+ extension (blender_manifest.toml). The core (exclone_addon.core) never imports bpy,
so the Blender layer is imported only when Blender registers the extension.
"""


def register():
    from .blender import operators
    operators.register()


def unregister():
    from .blender import operators
    operators.unregister()
