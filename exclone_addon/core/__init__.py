"""ExClone's pure core: numpy/scipy functions on arrays, no bpy. One module per step."""
