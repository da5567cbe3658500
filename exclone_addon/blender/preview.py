"""A contact sheet of a head's expressions: the neutral and up to 7 shape keys rendered from the
front (Workbench, or CPU Cycles where Workbench cannot render), one label per tile.

Renders the current scene, which it sets up for this (camera, resolution, world): meant for the
command line's throwaway session, not for a user's scene.
"""
import math
import tempfile
from pathlib import Path

import bpy
import cv2
import numpy as np

from ..core.errors import ExCloneError

# The neutral plus the first of these that were cloned, then any others, 8 tiles in all.
FAVOURITES = ("jawOpen", "eyeBlink_L", "mouthSmile_L", "browInnerUp", "browInnerUp_L",
              "mouthPucker", "cheekPuff", "cheekPuff_L", "mouthFunnel", "browDown_R",
              "noseSneer_L", "mouthFrown_L")
TILES = 8
TILES_PER_ROW = 4
TILE_SIZE = 320


def shown_names(names):
    """The shape keys a sheet shows (after the neutral): favourites first, 7 at most."""
    favourites = [n for n in FAVOURITES if n in names]
    others = [n for n in names if n not in favourites]
    return (favourites + others)[:TILES - 1]


def _render_tile(scene, path):
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    image = cv2.imread(str(path))
    if image is None:
        raise ExCloneError(f"preview: rendering produced no image ({scene.render.engine})")
    return image


def _setup_scene(scene, obj, vertices):
    """Orthographic front camera (looking along +Y, Blender's front view) framing the object."""
    matrix = np.array(obj.matrix_world)
    world = vertices @ matrix[:3, :3].T + matrix[:3, 3]
    low, high = world.min(axis=0), world.max(axis=0)
    center, size = (low + high) / 2, high - low
    camera = bpy.data.objects.new("ExClone preview camera", bpy.data.cameras.new("ExClone preview"))
    scene.collection.objects.link(camera)
    camera.data.type = 'ORTHO'
    camera.data.ortho_scale = 1.08 * max(size[0], size[2])
    camera.data.clip_end = 10 * (size.max() + 1)
    camera.location = (center[0], low[1] - 2 * size.max() - 0.1, center[2])
    camera.rotation_euler = (math.pi / 2, 0.0, 0.0)
    scene.camera = camera
    scene.render.resolution_x = scene.render.resolution_y = TILE_SIZE
    scene.render.resolution_percentage = 100
    scene.render.image_settings.file_format = 'PNG'
    scene.world = bpy.data.worlds.new("ExClone preview")  # light grey background (and ambient)
    scene.world.color = (0.6, 0.6, 0.6)
    scene.render.engine = 'BLENDER_WORKBENCH'


def _use_cycles(scene):
    """CPU Cycles with few samples: the fallback when Workbench cannot render here."""
    scene.render.engine = 'CYCLES'
    scene.cycles.device = 'CPU'
    scene.cycles.samples = 16
    scene.cycles.use_denoising = False
    scene.render.tile_size = 64
    sun = bpy.data.objects.new("ExClone preview sun", bpy.data.lights.new("ExClone sun", 'SUN'))
    sun.rotation_euler = (math.radians(60), 0.0, math.radians(-25))
    scene.collection.objects.link(sun)


def _rendered_tiles(scene, key_blocks, shown):
    """One image per name (the neutral: every key at 0); falls back to Cycles when Workbench
    gives no image or a flat one for the first tile."""
    tiles = []
    with tempfile.TemporaryDirectory(prefix="exclone_preview_") as tmp:
        for i, name in enumerate(shown):
            for block in key_blocks[1:]:
                block.value = 1.0 if block.name == name else 0.0
            tile_path = Path(tmp) / f"{i}.png"
            try:
                tile = _render_tile(scene, tile_path)
            except RuntimeError:
                tile = None
            if i == 0 and scene.render.engine == 'BLENDER_WORKBENCH' and (
                    tile is None or tile.std() < 1.0):
                _use_cycles(scene)
                tile = _render_tile(scene, tile_path)
            if tile is None:
                raise ExCloneError(f"preview: {scene.render.engine} could not render")
            tiles.append(tile)
    for block in key_blocks[1:]:
        block.value = 0.0
    return tiles


def _labelled_sheet(tiles, names):
    tiles = tiles + [np.full_like(tiles[0], 255)] * (-len(tiles) % TILES_PER_ROW)
    for tile, name in zip(tiles, names):
        for colour, thickness in (((255, 255, 255), 3), ((0, 0, 0), 1)):
            cv2.putText(tile, name, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, colour, thickness,
                        cv2.LINE_AA)
    rows = [np.hstack(tiles[r:r + TILES_PER_ROW]) for r in range(0, len(tiles), TILES_PER_ROW)]
    return np.vstack(rows)


def contact_sheet(obj, vertices, names):
    """(BGR image, render engine used): the neutral and up to 7 of the object's shape keys
    `names` (shown_names), rendered in the current scene. vertices: the object's mesh (local)."""
    scene = bpy.context.scene
    _setup_scene(scene, obj, vertices)
    shown = ["neutral"] + shown_names(names)
    tiles = _rendered_tiles(scene, obj.data.shape_keys.key_blocks, shown)
    return _labelled_sheet(tiles, shown), scene.render.engine
