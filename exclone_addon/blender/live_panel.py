"""The "Drive from Webcam" sub-panel of the ExClone sidebar tab."""
import bpy

from . import preferences, webcam_take


class EXCLONE_PT_webcam(bpy.types.Panel):
    bl_idname = "EXCLONE_PT_webcam"
    bl_label = "Drive from Webcam"
    bl_space_type = 'VIEW_3D'
    bl_region_type = 'UI'
    bl_category = "ExClone"
    bl_parent_id = "EXCLONE_PT_main"

    def draw(self, context):
        draw(self.layout, context)


def status_text():
    """The panel's status line: the running take's, else what the last take did."""
    if webcam_take.running is not None:
        return webcam_take.running.status
    if webcam_take.last_take is not None:
        try:
            return f"Last take: {webcam_take.last_take.summary()}"
        except ReferenceError:
            pass
    return "Not running"


def draw(layout, context):
    """The sub-panel's contents on `layout` (a UILayout, or anything with its methods)."""
    webcam = context.scene.exclone.webcam
    path = _draw_source(layout, context, webcam)
    _draw_take(layout, webcam, path)
    _draw_camera_calibration(layout, webcam)


def _draw_source(layout, context, webcam):
    """The source choice and its camera index or path; returns the path ("" for a camera)."""
    column = layout.column(align=True)
    column.prop(webcam, "source_type", text="")
    if webcam.source_type == 'CAMERA':
        column.prop(webcam, "camera_index")
        if webcam.camera_index < 0:
            column.label(text=f"Preferences' webcam: {preferences.camera_index(context)}")
        return ""
    if webcam.source_type == 'VIDEO':
        column.prop(webcam, "video_path", text="")
        return webcam.video_path
    column.prop(webcam, "image_folder", text="")
    return webcam.image_folder


def _draw_take(layout, webcam, path):
    """What the take drives, Start (or Stop while it runs), Calibrate, Refine and the status."""
    column = layout.column(align=True)
    column.prop(webcam, "key_set")
    column.prop(webcam, "head_target")
    armature = webcam.head_armature
    if webcam.head_target == 'BONE':
        column.prop(webcam, "head_armature")
        if armature is not None:
            column.prop_search(webcam, "head_bone", armature.data, "bones")
    row = layout.row(align=True)
    row.prop(webcam, "record", icon='REC')
    row.prop(webcam, "show_overlay", icon='IMAGE_DATA')
    layout.prop(webcam, "use_appearance")

    row = layout.row(align=True)
    if webcam_take.running is None:
        start = row.operator("exclone.drive_from_webcam", text="Start", icon='PLAY')
        start.source_type = webcam.source_type
        start.camera_index = webcam.camera_index
        start.filepath = path
        start.record = webcam.record
        start.key_set = webcam.key_set
        start.head_target = webcam.head_target
        start.armature = armature.name if armature is not None else ""
        start.bone = webcam.head_bone
        start.show_overlay = webcam.show_overlay
        start.use_appearance = webcam.use_appearance
    else:
        row.operator("exclone.stop_webcam", text="Stop", icon='PAUSE')
    row.operator("exclone.calibrate_neutral", text="Calibrate", icon='USER')
    layout.operator("exclone.refine_take", icon='MODIFIER')
    _draw_take_csv(layout, webcam, armature)
    layout.label(text=status_text(), icon='INFO')


def _draw_take_csv(layout, webcam, armature):
    """Import and Export Take CSV; an import drives the head rotation chosen above."""
    row = layout.row(align=True)
    importer = row.operator("exclone.import_take_csv", icon='IMPORT')
    importer.head_target = webcam.head_target
    importer.armature = armature.name if armature is not None else ""
    importer.bone = webcam.head_bone
    row.operator("exclone.export_take_csv", icon='EXPORT')


def _draw_camera_calibration(layout, webcam):
    box = layout.box()
    box.label(text="Camera Calibration", icon='CAMERA_DATA')
    box.prop(webcam, "chessboard_folder", text="")
    row = box.row(align=True)
    row.prop(webcam, "chessboard_columns", text="X")
    row.prop(webcam, "chessboard_rows", text="Y")
    box.prop(webcam, "chessboard_frames")
    calibrate = box.operator("exclone.calibrate_camera", icon='GRID')
    calibrate.directory = webcam.chessboard_folder
    calibrate.camera_frames = webcam.chessboard_frames
    calibrate.camera_index = webcam.camera_index
    calibrate.columns = webcam.chessboard_columns
    calibrate.rows = webcam.chessboard_rows
    if webcam.calibration_width:
        box.prop(webcam, "calibrated")
        box.label(text=f"{webcam.calibration_width} x {webcam.calibration_height}: "
                       f"fx {webcam.fx:.0f}, error {webcam.calibration_rms:.2f} px")


CLASSES = (EXCLONE_PT_webcam,)
register, unregister = bpy.utils.register_classes_factory(CLASSES)
