"""The panel's settings, stored per scene (bpy.types.Scene.exclone) so they are saved in the .blend."""
import bpy
from bpy.props import (BoolProperty, CollectionProperty, EnumProperty, IntProperty,
                       PointerProperty, StringProperty)

PRESET_ITEMS = [("fast", "Fast", "Coarse registration schedule (3 closest-point steps)"),
                ("balanced", "Balanced", "Default registration schedule (5 steps)"),
                ("precise", "Precise", "Finest registration schedule (7 steps), slowest")]
FORMULATION_ITEMS = [
    ("reduced", "Reduced", "Two-edge gradients, vertices only: faster, the default"),
    ("augmented", "4th Vertex", "Sumner's formulation with a fourth vertex per triangle: "
                                "about 3x slower registration")]
PARTS_ITEMS = [
    ("FOLLOW", "Follow", "Separate parts (eyes, teeth) without landmarks follow the nearest "
                         "face vertex"),
    ("STILL", "Keep Still", "Only the parts that carry landmarks get expressions; the other "
                            "parts keep their shape in every new shape key")]


def is_mesh(_settings, obj):
    return obj.type == 'MESH'


class EXCLONE_PG_expression(bpy.types.PropertyGroup):
    """One source expression in the selection list (`name` is the expression's name)."""
    selected: BoolProperty(name="Clone", description="Clone this expression", default=True)


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


CLASSES = (EXCLONE_PG_expression, EXCLONE_PG_settings)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.exclone = PointerProperty(type=EXCLONE_PG_settings)


def unregister():
    del bpy.types.Scene.exclone
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
