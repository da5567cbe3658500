"""ExClone: clone facial expressions (shape keys) from one head mesh onto another.

A Blender 4.2+ extension (blender_manifest.toml). The core (exclone_addon.core) never imports bpy,
so the Blender layer is imported only when Blender registers the extension.
"""


def _modules():
    """The Blender layer's modules in registration order (properties before what uses them)."""
    from .blender import (character_keys, live_operators, live_panel, operators, panel,
                          preferences, properties, take_csv)
    return (properties, preferences, operators, character_keys, live_operators, take_csv, panel,
            live_panel)


def register():
    for module in _modules():
        module.register()


def unregister():
    for module in reversed(_modules()):
        module.unregister()
