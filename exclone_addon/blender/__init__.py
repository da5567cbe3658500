"""ExClone's Blender layer: operators and mesh I/O on top of the bpy-free core."""
