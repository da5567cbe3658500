"""The "ExClone" tab of the 3D viewport's sidebar (N panel)."""
import bpy

from ..core.errors import ExCloneError
from ..core.reports import flips_phrase, stretch_phrase
from . import character
from . import landmarks as stored_landmarks
from . import workflow


class EXCLONE_UL_expressions(bpy.types.UIList):
    def draw_item(self, context, layout, data, item, icon, active_data, active_property, index):
        layout.prop(item, "selected", text=item.name)


def _engine_options(operator, settings):
    if settings.preset != 'DEFAULT':
        operator.preset = settings.preset
    operator.formulation = settings.formulation


class EXCLONE_PT_main(bpy.types.Panel):
    bl_idname = "EXCLONE_PT_main"
    bl_label = "ExClone"
    bl_space_type = 'VIEW_3D'
    bl_region_type = 'UI'
    bl_category = "ExClone"

    def draw(self, context):
        draw(self.layout, context)


def draw(layout, context):
    """The panel's contents on `layout` (a UILayout, or anything with its methods)."""
    settings = context.scene.exclone
    target = _draw_source_and_target(layout, context, settings)
    _draw_landmarks(layout, target)
    _draw_engine_buttons(layout, settings)
    _draw_measures(layout)
    _draw_expressions(layout, settings)
    _draw_options(layout, settings)


def _draw_source_and_target(layout, context, settings):
    """The source and target choices; returns the target the operators will use (or None)."""
    column = layout.column(align=True)
    column.label(text="Source")
    column.prop(settings, "source_mode", text="")
    if settings.source_mode != 'LIBRARY':
        column.prop(settings, "source", text="")
    column.label(text="Target")
    column.prop(settings, "target", text="")
    target = workflow.target_object(context)
    if settings.target is None:
        column.label(text=f"Active: {target.name}" if target is not None else "Active: nothing",
                     icon='INFO')
    if target is not None:
        column.label(text=_character_text(target, context.selected_objects), icon='OUTLINER')
    return target


def _character_text(target, selected):
    """Which meshes make the character the face is looked for on (the operators' rule)."""
    try:
        meshes = character.character_objects(target, selected)
    except ExCloneError:
        return "Character: no mesh"
    if len(meshes) == 1:
        return f"Character: '{meshes[0].name}' (1 mesh)"
    return f"Character: {len(meshes)} meshes (the face is found among them)"


def _draw_landmarks(layout, target):
    box = layout.box()
    box.label(text="Landmarks", icon='EMPTY_DATA')
    row = box.row(align=True)
    row.operator("exclone.auto_landmarks", icon='VIEWZOOM')
    row.operator("exclone.snap_landmarks", text="Snap", icon='SNAP_ON')
    row = box.row(align=True)
    row.operator("exclone.mirror_landmarks", text="Mirror L > R").from_side = "left"
    row.operator("exclone.clear_landmarks", text="Clear", icon='X')
    if target is not None and target.type == 'MESH' and stored_landmarks.IDS in target:
        kind = "edited" if stored_landmarks.is_edited(target) else "automatic"
        box.label(text=f"{len(stored_landmarks.stored(target))} {kind} landmarks on target")


def _draw_engine_buttons(layout, settings):
    """Register, Remove Preview, Clone, Generate ARKit and Remove ExClone Keys, with the panel's
    settings."""
    use_library = settings.source_mode == 'LIBRARY'
    column = layout.column(align=True)
    row = column.row(align=True)
    register = row.operator("exclone.register_faces", icon='MOD_SHRINKWRAP')
    register.use_library = use_library
    register.preview = settings.show_preview
    _engine_options(register, settings)
    row.prop(settings, "show_preview", text="", icon='HIDE_OFF')
    column.operator("exclone.remove_preview", icon='TRASH')
    clone = column.operator("exclone.clone_expressions", icon='SHAPEKEY_DATA')
    clone.use_library = use_library
    clone.prefix = settings.prefix
    clone.only_ticked = settings.use_selection
    clone.parts = settings.parts
    clone.replace_existing = settings.replace_existing
    _engine_options(clone, settings)
    arkit = column.operator("exclone.generate_arkit_shapes", icon='USER')
    arkit.replace_existing = settings.replace_existing
    _engine_options(arkit, settings)
    column.operator("exclone.remove_keys", icon='TRASH')


def _percent(value, digits=0):
    return "-" if value is None else f"{100 * value:.{digits}f}%"


def _draw_measures(layout):
    """The last Clone's measures, compact: each blink's lid gap (the other eye's beside it), the
    lips at jawOpen (and with mouthClose), the worst stretch and flips."""
    measured = workflow.last_measures
    if not measured:
        return
    found = measured["summary"]
    column = layout.box().column(align=True)
    column.label(text=f"Last clone: {measured['target']}", icon='INFO')
    for name in ("eyeBlink_L", "eyeBlink_R"):
        column.label(text=f"{name}: lids {_percent(found[f'{name}_gap'])} open, "
                          f"other {_percent(found[f'{name}_other_eye_gap'])}")
    jaw, closed = found["jawOpen_lip_gap"], found["jawOpen+mouthClose_lip_gap"]
    column.label(text=f"jawOpen: lips {_percent(jaw, 1)} of the face apart")
    column.label(text=f"with mouthClose: {_percent(closed, 1)}")
    if found["worst_edge_stretch"] is not None:
        column.label(text=stretch_phrase(found))
        column.label(text=flips_phrase(found))


def _foldout(layout, settings, shown):
    """A box headed by the boolean property `shown` as a fold-out arrow: the box when it is open,
    else None."""
    box = layout.box()
    is_open = getattr(settings, shown)
    box.prop(settings, shown, icon='DOWNARROW_HLT' if is_open else 'RIGHTARROW', emboss=False)
    return box if is_open else None


def _draw_expressions(layout, settings):
    box = _foldout(layout, settings, "show_expressions")
    if box is not None:
        box.prop(settings, "use_selection")
        box.operator("exclone.refresh_expressions", icon='FILE_REFRESH')
        box.template_list("EXCLONE_UL_expressions", "", settings, "expressions", settings,
                          "expression_index", rows=5)


def _draw_options(layout, settings):
    box = _foldout(layout, settings, "show_options")
    if box is not None:
        box.prop(settings, "preset")
        box.prop(settings, "formulation")
        box.prop(settings, "parts")
        box.prop(settings, "prefix")
        box.prop(settings, "replace_existing")


CLASSES = (EXCLONE_UL_expressions, EXCLONE_PT_main)
register, unregister = bpy.utils.register_classes_factory(CLASSES)
