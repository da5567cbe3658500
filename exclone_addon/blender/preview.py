"""A contact sheet of a head's expressions: the neutral and up to 7 shape keys rendered from the
front (Workbench, or CPU Cycles where Workbench cannot render), one label per tile, and a row of
close-ups: the eyes at rest and closing, the mouth at rest and opening (where a lid that folds
or a torn mouth corner shows, which a whole-head tile is too small to show).

Renders the current scene, which it sets up for this (camera, resolution, world): meant for the
command line's throwaway session, not for a user's scene.
"""
import math
import tempfile
from dataclasses import dataclass
from pathlib import Path

import bpy
import cv2
import numpy as np
from mathutils import Matrix

from ..core.errors import ExCloneError
from ..core.expression_measures import FaceAxes, Openings, close_up_expressions
from ..core.face_render import Camera

# The neutral plus the first of these that were cloned, then any others, 8 tiles in all.
FAVOURITES = ("jawOpen", "eyeBlink_L", "mouthSmile_L", "browInnerUp", "browInnerUp_L",
              "mouthPucker", "cheekPuff", "cheekPuff_L", "mouthFunnel", "browDown_R",
              "noseSneer_L", "mouthFrown_L")
TILES = 8
TILES_PER_ROW = 4
TILE_SIZE = 320


@dataclass(frozen=True)
class CloseUp:
    """A close-up tile: the shape key `name` (None: the neutral) seen along -forward, `up` up,
    `width` across, centred on `centre` (world space)."""
    label: str
    name: object
    centre: tuple
    forward: tuple
    up: tuple
    width: float


# Close-ups: the eyes across this many times the outer eye corners' distance, the mouth this many
# times the mouth corners'.
EYES_ACROSS = 1.4
MOUTH_ACROSS = 2.2


def eye_and_mouth_close_ups(points, measures, names):
    """The CloseUps of a sheet: the eyes at rest and in the expression of `names` that closes an
    eye furthest, the mouth at rest and in the one that opens it furthest (close_up_expressions;
    a region without one is left out). points: {landmark name: (3,) world point} of the
    automatic landmarks (none without them); measures: measure_expressions' result."""
    if any(name not in points for name in Openings.NEEDED + ("mouth_corner_left",
                                                             "mouth_corner_right")):
        return []
    axes = FaceAxes(points)
    eyes_name, mouth_name = close_up_expressions(measures, names)
    found = []
    for region, name, ends, across in (("eyes", eyes_name, "eye_outer", EYES_ACROSS),
                                       ("mouth", mouth_name, "mouth_corner", MOUTH_ACROSS)):
        if name is None:
            continue
        left, right = points[f"{ends}_left"], points[f"{ends}_right"]
        width = across * float(np.linalg.norm(left - right))
        found += [CloseUp(f"{region}: {label}", key, tuple((left + right) / 2),
                          tuple(axes.forward), tuple(axes.up), width)
                  for label, key in (("neutral", None), (name, name))]
    return found


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
    sun = bpy.data.objects.new("ExClone preview sun", bpy.data.lights.new("ExClone sun", 'SUN'))
    sun.rotation_euler = (math.radians(60), 0.0, math.radians(-25))
    scene.collection.objects.link(sun)


def _aim(camera, close_up):
    """The camera looking along -forward at the close-up's centre, its up up (the axes of
    face_render's camera, which Blender's camera shares: it looks along its -Z)."""
    axes = Camera.looking(close_up.centre, close_up.forward, close_up.up, close_up.width).axes
    pose = np.identity(4)
    pose[:3, :3] = axes.T                       # columns: right, up, back
    pose[:3, 3] = np.asarray(close_up.centre, float) + axes[2] * 10 * close_up.width
    camera.matrix_world = Matrix(pose.tolist())      # rows
    camera.data.ortho_scale = close_up.width
    camera.data.clip_end = 20 * close_up.width + 1


def _rendered_tiles(scene, key_blocks, shown, poses=None):
    """One image per name (the neutral: every key at 0), the camera aimed by poses[i]
    (_aim; None: as it is); falls back to Cycles when Workbench gives no image or a flat one
    for the first tile."""
    tiles = []
    with tempfile.TemporaryDirectory(prefix="exclone_preview_") as tmp:
        for i, name in enumerate(shown):
            if poses and poses[i] is not None:
                _aim(scene.camera, poses[i])
            for block in key_blocks[1:]:
                block.value = 1.0 if block.name == name else 0.0
            tile_path = Path(tmp) / f"{i}.png"
            try:
                tile = _render_tile(scene, tile_path)
            except RuntimeError:
                tile = None
            if i == 0 and not poses and scene.render.engine == 'BLENDER_WORKBENCH' and (
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


def contact_sheet(obj, vertices, names, close_ups=()):
    """(BGR image, render engine used): the neutral and up to 7 of the object's shape keys
    `names` (shown_names), rendered in the current scene, then a row of close_ups (CloseUp).
    vertices: the object's mesh (local)."""
    scene = bpy.context.scene
    _setup_scene(scene, obj, vertices)
    shown = ["neutral"] + shown_names(names)
    key_blocks = obj.data.shape_keys.key_blocks
    tiles = _rendered_tiles(scene, key_blocks, shown)
    labels = list(shown)
    if close_ups:               # on a row of their own
        blank = -len(tiles) % TILES_PER_ROW
        tiles, labels = tiles + [np.full_like(tiles[0], 255)] * blank, labels + [""] * blank
        tiles += _rendered_tiles(scene, key_blocks, [c.name or "neutral" for c in close_ups],
                                 list(close_ups))
        labels += [c.label for c in close_ups]
    return _labelled_sheet(tiles, labels), scene.render.engine
