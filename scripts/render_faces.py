"""Render a face posed with known expression weights and a known head pose through a known camera
(background Blender, Workbench): the known-answer frames of the rendered takes the tracking tests
track through the image models (blender_tests/helpers/takes.py).

The head is an ICT-FaceKit topology mesh (the bundled library, or an ICT identity): skin, lips
and brows coloured per vertex, white eyeballs with a dark iris and pupil, dark mouth socket,
lashes; the see-through shells around the eyes (lacrimal fluid, occlusion) are left out. Or a
character's meshes (character_colours): its skin with the lips painted, its eyes, brows,
lashes, teeth and tongue coloured as the ICT head's are.
The camera is OpenCV's pinhole (x right, y down, z forward) at Blender's origin: a point p in
camera space is placed at (p_x, -p_y, -p_z), and the image is what core.tracking.Camera with
the same intrinsics projects.
"""
import bpy
import cv2
import numpy as np
from scipy.spatial import cKDTree

IMAGE_SIZE = (640, 480)
SKIN = (0.80, 0.58, 0.46)
LIPS = (0.66, 0.34, 0.32)
BROWS = (0.25, 0.17, 0.12)
SCLERA = (0.92, 0.90, 0.88)
IRIS = (0.30, 0.20, 0.12)
PUPIL = (0.03, 0.03, 0.03)
MOUTH = (0.25, 0.08, 0.08)
TEETH = (0.90, 0.88, 0.80)
LASHES = (0.08, 0.06, 0.05)
# FaceMesh's brow and lip points (its own ids): what the brows and lips are painted around.
BROW_POINTS = (70, 63, 105, 66, 107, 55, 65, 52, 53, 46, 300, 293, 334, 296, 336, 285, 295,
               282, 283, 276)
LIP_POINTS = (61, 146, 91, 181, 84, 17, 314, 405, 321, 375, 291, 185, 40, 39, 37, 0, 267, 269,
              270, 409, 78, 95, 88, 178, 87, 14, 317, 402, 318, 324, 308, 191, 80, 81, 82, 13,
              312, 311, 310, 415)
# Workbench's own studio lights (what the appearance model's training takes are lit by).
STUDIO_LIGHTS = ("Default", "basic.sl", "outdoor.sl", "paint.sl", "rim.sl", "studio.sl")
IRIS_RADIUS_DEG = 30.0        # angular radius of the iris on the eyeball
PUPIL_RADIUS_DEG = 13.0


def vertex_colours(vertices, parts, located_points):
    """(n, 3) linear RGB per vertex of an ICT-topology head (vertices in its neutral pose).

    parts: ICT's {name: (start, stop)} vertex ranges; located_points: (468, 3) FaceMesh's points
    located on the neutral skin. Lips: skin within 5% of the eye distance of a lip point;
    brows: skin within 7% of it of a brow point.
    """
    colours = np.tile(SKIN, (len(vertices), 1))
    start, stop = parts["face"]
    _paint(colours[start:stop], vertices[start:stop], located_points,
           ((LIP_POINTS, LIPS, 0.05), (BROW_POINTS, BROWS, 0.07)))
    for name, colour in (("mouth_socket", MOUTH), ("gums_and_tongue", MOUTH), ("teeth", TEETH),
                         ("eye_sockets", MOUTH), ("eyelashes", LASHES)):
        start, stop = parts[name]
        colours[start:stop] = colour
    start, stop = parts["eyeballs"]
    colours[start:stop] = _eyeball_colours(vertices[start:stop])
    return colours


def character_colours(parts, located_points):
    """(n, 3) linear RGB per vertex of a character's meshes (parts: [(object name, vertices
    (k, 3) in model space, the face looking along +Z about x = 0)], in that order): eyes, brows,
    lashes, teeth and tongue by their names (MakeHuman's: Eye_L, Eyes, Eyebrows, Eyelashes,
    Teeth, Tongue), the rest skin with the lips painted around located_points' (the tracker's
    468 points on it)."""
    coloured = []
    for name, vertices in parts:
        name = name.lower()
        colours = np.tile(SKIN, (len(vertices), 1))
        if "brow" in name:
            colours[:] = BROWS
        elif "lash" in name:
            colours[:] = LASHES
        elif name.startswith("eye"):
            colours = _eyeball_colours(vertices)
        elif "teeth" in name:
            colours[:] = TEETH
        elif "tongue" in name:
            colours[:] = MOUTH
        else:
            _paint(colours, vertices, located_points, ((LIP_POINTS, LIPS, 0.05),))
        coloured.append(colours)
    return np.vstack(coloured)


def _paint(colours, skin, located_points, features):
    """Paints `colours` (of the vertices `skin`) in place: each feature (FaceMesh point ids,
    colour, reach) within its reach (a fraction of the eye distance) of its located points."""
    eye_distance = np.linalg.norm(located_points[33] - located_points[263])
    for ids, colour, reach in features:
        near = cKDTree(located_points[list(ids)]).query(skin)[0] < reach * eye_distance
        colours[near] = colour


def _eyeball_colours(eyeballs):
    """Sclera, iris and pupil by the angle from each eyeball's forward (+Z) axis (the eyeballs
    either side of x = 0; one alone too)."""
    colours = np.tile(SCLERA, (len(eyeballs), 1))
    for side in (eyeballs[:, 0] < 0, eyeballs[:, 0] >= 0):
        if not side.any():
            continue
        points = eyeballs[side]
        centre = 0.5 * (points.min(axis=0) + points.max(axis=0))
        direction = points - centre
        cos = direction[:, 2] / np.maximum(np.linalg.norm(direction, axis=1), 1e-12)
        angle = np.degrees(np.arccos(np.clip(cos, -1, 1)))
        c = colours[side]
        c[angle < IRIS_RADIUS_DEG] = IRIS
        c[angle < PUPIL_RADIUS_DEG] = PUPIL
        colours[side] = c
    return colours


class FaceRenderer:
    """A background-Blender scene holding one head mesh and a pinhole camera; render(points)
    places the head's vertices (camera space, OpenCV axes) and returns the BGR image.

    light_turn: None, the studio light as Workbench lights the view (from the camera's side, as
    the appearance map's training takes are lit); else the light fixed in the scene and turned
    this many radians about the vertical (a window to one side)."""

    def __init__(self, triangles, colours, image_size=IMAGE_SIZE, focal_px=None, light="STUDIO",
                 studio_light="Default", light_turn=None):
        bpy.ops.wm.read_factory_settings(use_empty=True)
        width, height = image_size
        self.image_size = (int(width), int(height))
        self.focal_px = float(focal_px if focal_px is not None else max(width, height))
        scene = bpy.context.scene
        self.scene = scene
        mesh = bpy.data.meshes.new("face")
        n = int(np.max(triangles)) + 1
        mesh.vertices.add(n)
        mesh.loops.add(3 * len(triangles))
        mesh.polygons.add(len(triangles))
        mesh.loops.foreach_set("vertex_index", np.asarray(triangles, dtype=np.int32).ravel())
        mesh.polygons.foreach_set("loop_start", np.arange(0, 3 * len(triangles), 3, dtype=np.int32))
        mesh.polygons.foreach_set("loop_total", np.full(len(triangles), 3, dtype=np.int32))
        mesh.update()
        mesh.polygons.foreach_set("use_smooth", np.ones(len(triangles), dtype=bool))
        attribute = mesh.color_attributes.new("colour", 'FLOAT_COLOR', 'POINT')
        rgba = np.column_stack((colours, np.ones(len(colours))))
        attribute.data.foreach_set("color", rgba.astype(np.float32).ravel())
        self.mesh = mesh
        self.object = bpy.data.objects.new("face", mesh)
        scene.collection.objects.link(self.object)
        self._setup_camera(scene)
        self._setup_look(scene, light, studio_light, light_turn)

    def _setup_camera(self, scene):
        width, height = self.image_size
        camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
        scene.collection.objects.link(camera)
        camera.data.sensor_fit = 'HORIZONTAL'
        camera.data.sensor_width = 36.0
        camera.data.lens = 36.0 * self.focal_px / width
        camera.data.clip_start = 1.0
        camera.data.clip_end = 10000.0
        camera.location = (0.0, 0.0, 0.0)
        camera.rotation_euler = (0.0, 0.0, 0.0)
        scene.camera = camera
        scene.render.resolution_x, scene.render.resolution_y = width, height
        scene.render.resolution_percentage = 100

    def _setup_look(self, scene, light, studio_light, light_turn):
        scene.render.engine = 'BLENDER_WORKBENCH'
        shading = scene.display.shading
        shading.light = light
        shading.studio_light = studio_light     # one of Workbench's own (STUDIO_LIGHTS)
        if light_turn is not None:
            shading.use_world_space_lighting = True
            shading.studiolight_rotate_z = float(light_turn)
        shading.color_type = 'VERTEX'
        shading.show_specular_highlight = False
        shading.show_cavity = False
        scene.display.render_aa = 'FXAA'    # 0.33 s a frame; '8' samples: 1.2 s
        world = bpy.data.worlds.new("world")
        world.color = (0.35, 0.38, 0.42)
        scene.world = world
        scene.view_settings.view_transform = 'Standard'

    def render(self, camera_points, path):
        """camera_points: (n, 3) the head's vertices in camera space (OpenCV axes); writes the
        PNG to `path` and returns it as an 8-bit BGR image."""
        placed = np.column_stack((camera_points[:, 0], -camera_points[:, 1], -camera_points[:, 2]))
        self.mesh.vertices.foreach_set("co", placed.astype(np.float32).ravel())
        self.mesh.update()
        self.scene.render.filepath = str(path)
        bpy.ops.render.render(write_still=True)
        image = cv2.imread(str(path))
        if image is None:
            raise RuntimeError(f"Blender wrote no image to {path}")
        return image


def rendered_triangles(triangles, parts):
    """The triangles worth rendering: all but the see-through shells around the eyes."""
    start, stop = parts["eye_blend_occlusion"]
    hidden = np.any((triangles >= start) & (triangles < stop), axis=1)
    return triangles[~hidden]


def head_pose_points(vertices, rotation, translation, centre):
    """A head's vertices (model space: +Y up, looking along +Z) turned by `rotation` (a
    scipy Rotation, model -> camera, including the half turn that faces the camera) about
    `centre` and moved to `translation` (camera space)."""
    return rotation.apply(np.asarray(vertices) - centre) + translation
