"""The panel's settings, stored per scene (bpy.types.Scene.exclone) so they are saved in the .blend."""
import bpy
from bpy.props import (BoolProperty, CollectionProperty, EnumProperty, FloatProperty,
                       IntProperty, PointerProperty, StringProperty)

PRESET_ITEMS = [("fast", "Fast", "Coarse registration schedule (3 closest-point steps)"),
                ("balanced", "Balanced", "Default registration schedule (5 steps)"),
                ("precise", "Precise", "Finest registration schedule (7 steps), slowest")]
FORMULATION_ITEMS = [
    ("reduced", "Reduced", "Two-edge gradients, vertices only: faster, the default"),
    ("augmented", "4th Vertex", "Sumner's formulation with a fourth vertex per triangle: "
                                "about 3x slower registration")]
PARTS_ITEMS = [
    ("FOLLOW", "Follow Rigidly", "Separate parts (eyes, teeth) without landmarks move as rigid "
                                 "bodies with the face vertices around them"),
    ("STILL", "Keep Still", "Only the parts that carry landmarks get expressions; the other "
                            "parts keep their shape in every new shape key")]


WEBCAM_SOURCE_ITEMS = [("CAMERA", "Camera", "A webcam, by its index"),
                       ("VIDEO", "Video File", "A video file, read at its own frame rate"),
                       ("FOLDER", "Image Folder", "A folder of images, sorted by name")]
KEY_SET_ITEMS = [("ALL", "All Shape Keys", "Every shape key of the avatar except the basis"),
                 ("ARKIT", "ARKit Names", "Only the shape keys named like Apple's ARKit blend "
                                          "shapes (and ICT-FaceKit's _L/_R halves)")]
HEAD_TARGET_ITEMS = [("NONE", "None", "The head rotation is not applied"),
                     ("OBJECT", "Avatar Object", "Rotate the avatar object itself"),
                     ("BONE", "Armature Bone", "Rotate a bone of an armature")]


def is_mesh(_settings, obj):
    return obj.type == 'MESH'


def is_armature(_settings, obj):
    return obj.type == 'ARMATURE'


class EXCLONE_PG_expression(bpy.types.PropertyGroup):
    """One source expression in the selection list (`name` is the expression's name)."""
    selected: BoolProperty(name="Clone", description="Clone this expression", default=True)


# Drive from Webcam's "Read the Face's Image", on the panel's settings and on the operator.
APPEARANCE_OPTION = dict(
    name="Read the Face's Image", default=True,
    description="Read expressions from the face's image as well as from its points (off: the "
                "points and the eyes alone)")


class EXCLONE_PG_webcam(bpy.types.PropertyGroup):
    """Drive from Webcam: the panel's choices and the scene's chessboard camera calibration."""
    source_type: EnumProperty(name="Source", items=WEBCAM_SOURCE_ITEMS, default="CAMERA")
    camera_index: IntProperty(
        name="Camera", min=-1, max=63, default=-1,
        description="Index of the camera (-1: the webcam chosen in the add-on preferences)")
    video_path: StringProperty(name="Video", subtype='FILE_PATH',
                               description="Video file to track")
    image_folder: StringProperty(name="Folder", subtype='DIR_PATH',
                                 description="Folder of images to track, in name order")
    record: BoolProperty(
        name="Record", default=False,
        description="Insert keyframes at scene frames that follow the take's time at the "
                    "scene's frame rate (otherwise the values are only shown)")
    key_set: EnumProperty(name="Shape Keys", items=KEY_SET_ITEMS, default="ALL")
    head_target: EnumProperty(name="Head Rotation", items=HEAD_TARGET_ITEMS, default="NONE")
    head_armature: PointerProperty(name="Armature", type=bpy.types.Object, poll=is_armature,
                                   description="Armature whose bone follows the head")
    head_bone: StringProperty(name="Bone", description="Bone that follows the head")
    show_overlay: BoolProperty(
        name="Camera Preview", default=True,
        description="Show the camera image with the tracked landmarks in the viewport")
    use_appearance: BoolProperty(**APPEARANCE_OPTION)
    chessboard_folder: StringProperty(
        name="Chessboards", subtype='DIR_PATH',
        description="Folder of photographs of a printed chessboard taken with the webcam")
    chessboard_columns: IntProperty(name="Inner Corners X", min=3, max=30, default=9)
    chessboard_rows: IntProperty(name="Inner Corners Y", min=3, max=30, default=6)
    chessboard_frames: IntProperty(
        name="Camera Frames", min=0, max=200, default=0,
        description="0: read the chessboard folder; N: grab N frames from the camera instead")
    # The last chessboard calibration: pinhole intrinsics at the image size it was made at.
    calibrated: BoolProperty(name="Use Calibration", default=False,
                             description="Takes use the chessboard calibration below")
    fx: FloatProperty(name="fx", min=0.0)
    fy: FloatProperty(name="fy", min=0.0)
    cx: FloatProperty(name="cx")
    cy: FloatProperty(name="cy")
    calibration_width: IntProperty(name="Width", min=0)
    calibration_height: IntProperty(name="Height", min=0)
    calibration_rms: FloatProperty(name="Reprojection Error", min=0.0, subtype='PIXEL')


class EXCLONE_PG_settings(bpy.types.PropertyGroup):
    source_mode: EnumProperty(
        name="Source",
        items=[("OBJECT", "Mesh Object", "A mesh object with shape keys"),
               ("LIBRARY", "Built-in ARKit Library",
                "The bundled ICT-FaceKit library of 57 ARKit-style expressions")],
        default="OBJECT")
    source: PointerProperty(
        name="Source Object", type=bpy.types.Object, poll=is_mesh,
        description="Mesh whose shape keys are cloned (its base mesh is read, not the result "
                    "of its modifiers). Empty: the selected mesh with shape keys")
    target: PointerProperty(
        name="Target Object", type=bpy.types.Object, poll=is_mesh,
        description="Mesh that receives the shape keys (its basis is read, modifiers are "
                    "ignored). Empty: the active object")
    preset: EnumProperty(
        name="Quality",
        items=[("DEFAULT", "Preferences Default", "The preset chosen in the add-on preferences")]
        + PRESET_ITEMS,
        default="DEFAULT")
    formulation: EnumProperty(name="Formulation", items=FORMULATION_ITEMS, default="reduced")
    parts: EnumProperty(name="Other Parts", items=PARTS_ITEMS, default="FOLLOW")
    prefix: StringProperty(name="Prefix", description="Put this before every new shape key's name")
    replace_existing: BoolProperty(
        name="Replace Existing",
        description="Overwrite shape keys that already have an expression's name "
                    "(otherwise they are kept and skipped)")
    expressions: CollectionProperty(type=EXCLONE_PG_expression)
    expression_index: IntProperty(name="Expression", min=0)
    use_selection: BoolProperty(
        name="Only Ticked Expressions",
        description="Clone only the expressions ticked in the list (Refresh fills it from the "
                    "source)")
    show_preview: BoolProperty(
        name="Preview Registration", default=True,
        description="Register shows the registered source as a temporary wireframe object")
    show_options: BoolProperty(name="Options", default=False)
    show_expressions: BoolProperty(name="Expressions", default=False)
    webcam: PointerProperty(type=EXCLONE_PG_webcam)


CLASSES = (EXCLONE_PG_expression, EXCLONE_PG_webcam, EXCLONE_PG_settings)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.exclone = PointerProperty(type=EXCLONE_PG_settings)


def unregister():
    del bpy.types.Scene.exclone
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
