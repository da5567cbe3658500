"""Operators: clone expressions from a selected mesh (or the built-in library) onto the active one."""
import time

import bpy
from bpy.props import BoolProperty, EnumProperty

from ..core.cloning import CloneSettings, clone_expressions
from ..core.errors import Cancelled, ExCloneError
from ..core.library import load_library
from . import mesh_io


def _source_candidates(context, target):
    return [obj for obj in context.selected_objects
            if obj != target and obj.type == 'MESH' and obj.data.shape_keys is not None
            and len(obj.data.shape_keys.key_blocks) > 1]


def summary(added, replaced, skipped, seconds, quality):
    """One-line report, e.g. "52 shape keys added in 1.8 s, fit error 0.2%"."""
    parts = [f"{len(added)} shape keys added"]
    if replaced:
        parts.append(f"{len(replaced)} replaced")
    if skipped:
        shown = ", ".join(skipped[:3]) + (", ..." if len(skipped) > 3 else "")
        parts.append(f"{len(skipped)} skipped (already exist: {shown})")
    text = ", ".join(parts) + f" in {seconds:.1f} s"
    fit = quality.get("registration_mean_distance_rel")
    if fit is not None:
        text += f", fit error {100 * fit:.2g}%"
    return text


class EXCLONE_OT_clone_expressions(bpy.types.Operator):
    """Clone the expressions (shape keys) of the selected source mesh, or of the built-in
    library, onto the active mesh as new shape keys"""
    bl_idname = "exclone.clone_expressions"
    bl_label = "Clone Expressions"
    bl_options = {'REGISTER', 'UNDO'}

    use_library: BoolProperty(
        name="Built-in Library",
        description="Use the bundled ICT-FaceKit ARKit expressions as the source instead of a "
                    "selected mesh with shape keys",
        default=False)
    replace_existing: BoolProperty(
        name="Replace Existing",
        description="Overwrite shape keys that already have an expression's name "
                    "(otherwise they are kept and skipped)",
        default=False)
    preset: EnumProperty(
        name="Quality",
        items=[("fast", "Fast", "Coarse registration schedule"),
               ("balanced", "Balanced", "Default registration schedule"),
               ("precise", "Precise", "Finest registration schedule, slowest")],
        default="balanced")

    @classmethod
    def poll(cls, context):
        if context.mode != 'OBJECT':
            cls.poll_message_set("Switch to Object Mode first")
            return False
        target = context.active_object
        if target is None or target.type != 'MESH':
            cls.poll_message_set("Make the target head the active object (it must be a mesh)")
            return False
        return True

    def _source(self, context, target):
        if self.use_library:
            library = load_library()
            return library.mesh, library.names, library.deltas
        candidates = _source_candidates(context, target)
        if not candidates:
            raise ExCloneError("Select a source mesh with shape keys as well as the target "
                               "(active), or enable Built-in Library")
        if len(candidates) > 1:
            raise ExCloneError("Several selected meshes have shape keys ("
                               + ", ".join(obj.name for obj in candidates)
                               + "): select only one source")
        source = candidates[0]
        names, deltas = mesh_io.shape_keys_from_object(source, what="source")
        return mesh_io.mesh_from_object(source, what="source"), names, deltas

    def execute(self, context):
        target = context.active_object
        window_manager = context.window_manager
        started = time.perf_counter()
        window_manager.progress_begin(0.0, 1.0)
        try:
            source_mesh, names, deltas = self._source(context, target)
            existing = target.data.shape_keys.key_blocks.keys() if target.data.shape_keys else []
            skipped = [] if self.replace_existing else [n for n in names if n in existing]
            wanted = [i for i, name in enumerate(names) if name not in skipped]
            if not wanted:
                self.report({'WARNING'}, f"All {len(names)} expressions already exist as shape "
                                         "keys on the target; enable Replace Existing to redo them")
                return {'CANCELLED'}
            result = clone_expressions(
                source_mesh, deltas[wanted], [names[i] for i in wanted],
                mesh_io.mesh_from_object(target, what="target"),
                settings=CloneSettings(preset=self.preset),
                progress=lambda fraction, message: window_manager.progress_update(fraction))
            added, replaced, also_skipped = mesh_io.write_shape_keys(
                target, result.names, result.deltas, replace_existing=self.replace_existing)
        except ExCloneError as exc:
            self.report({'ERROR'}, str(exc))
            return {'CANCELLED'}
        except Cancelled:
            self.report({'WARNING'}, "Cancelled; nothing was changed")
            return {'CANCELLED'}
        finally:
            window_manager.progress_end()
        self.report({'INFO'}, summary(added, replaced, skipped + also_skipped,
                                      time.perf_counter() - started, result.quality))
        return {'FINISHED'}


def _menu_entry(self, context):
    self.layout.operator(EXCLONE_OT_clone_expressions.bl_idname)


_register_classes, _unregister_classes = bpy.utils.register_classes_factory(
    (EXCLONE_OT_clone_expressions,))


def register():
    _register_classes()
    bpy.types.VIEW3D_MT_object.append(_menu_entry)


def unregister():
    bpy.types.VIEW3D_MT_object.remove(_menu_entry)
    _unregister_classes()
