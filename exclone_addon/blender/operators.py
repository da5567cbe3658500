"""Operators: landmarks, registration and cloning of expressions onto the target character.

The target is the character of the scene's ExClone target or of the active object (any of its
objects, or its empty parent; without a hierarchy, the selected meshes): its face is found and
only the head of the face's object is solved (workflow.resolve_target). The source is the
built-in library, the scene's source object or the selected mesh with shape keys. Every operator checks
its input before it changes anything, and is one undo step. Whatever goes wrong (a user error, a
cancel, a bug) is reported as one line and the operator returns CANCELLED.
"""
import time
from dataclasses import dataclass

import bpy
from bpy.props import BoolProperty, EnumProperty, StringProperty

from ..core.errors import Cancelled, ExCloneError
from ..core.library import ARKIT_BLENDSHAPES, arkit_blendshapes
from ..core.mesh import PolyMesh
from ..core.reports import fit_error, measures_clause, summary
from . import landmarks as stored_landmarks
from . import character, character_keys, mesh_io, workflow
from .properties import FORMULATION_ITEMS, PARTS_ITEMS, PRESET_ITEMS
from .reporting import failed, in_object_mode, reporting

PREVIEW_TAG = "exclone_preview"
PREVIEW_NAME = "ExClone registration preview"


def _poll_target(cls, context):
    """Object Mode and a mesh target, else False with the reason as the button's tooltip."""
    if not in_object_mode(cls, context):
        return False
    target = workflow.target_object(context)
    if target is None:
        cls.poll_message_set("Nothing selected: make the character (or its head) the active "
                             "object")
        return False
    if target.type != 'MESH' and not character.family(target):
        cls.poll_message_set(f"'{target.name}' is not a mesh and has no mesh objects under it: "
                             "select the character's mesh objects")
        return False
    return True


def _poll_source(cls, context):
    """False (with a reason) when the scene's chosen source object cannot be a source."""
    settings = context.scene.exclone
    source = settings.source
    if settings.source_mode == 'OBJECT' and source is not None:
        if source == workflow.target_object(context):
            cls.poll_message_set(f"'{source.name}' is both source and target")
            return False
        if not workflow.has_shape_keys(source):
            cls.poll_message_set(f"Source '{source.name}' has no shape keys")
            return False
    return True


@dataclass
class Plan:
    """An engine operator's checked inputs, and what to do with the engine's result."""
    inputs: tuple                 # run_engine's (source, CharacterFace, landmarks, settings, transfer)
    target: object                # the face's object (its mesh must not change while it runs)
    finish: object                # callable(workflow.Run) -> the operator's return set


class _FindsTheFaceFirst:
    """From the UI (invoke with a window) the faces the operator will look for
    (self.face_searches) are found in a worker first (workflow.FaceSearch, remembered by
    character_face), so Blender does not freeze for the face finding's renders (1-3 s on a
    character the first time); then self.after_search(context) runs on the main thread: a set
    ends the operator, None hands the modal events to self.modal_work. Elsewhere (scripts,
    background Blender) execute() runs at once. Esc cancels the search."""

    _invoked = None

    def started(self):
        """When this run started: at invoke, so that the face search counts in the reported
        time; else now (execute called directly, or again from the redo panel)."""
        started, self._invoked = self._invoked or time.perf_counter(), None
        return started

    def invoke(self, context, event):
        if bpy.app.background or context.window is None:
            return self.execute(context)
        self._invoked = time.perf_counter()
        try:
            self._search = workflow.FaceSearch(self.face_searches(context)).start()
        except Exception as exc:
            return failed(self, exc)
        window_manager = context.window_manager
        self._timer = window_manager.event_timer_add(0.1, window=context.window)
        window_manager.progress_begin(0.0, 1.0)
        window_manager.modal_handler_add(self)
        context.workspace.status_text_set("ExClone: finding the face... (Esc cancels)")
        return {'RUNNING_MODAL'}

    def _end_modal(self, context):
        context.window_manager.event_timer_remove(self._timer)
        context.window_manager.progress_end()
        context.workspace.status_text_set(None)

    def modal(self, context, event):
        if self._search is None:
            return self.modal_work(context, event)
        if event.type == 'ESC':             # the search ends by itself; its faces are remembered
            self._end_modal(context)
            return failed(self, Cancelled())
        if event.type != 'TIMER' or not self._search.done:
            return {'PASS_THROUGH'}
        self._search = None
        ended = self.after_search(context)
        if ended is not None:
            self._end_modal(context)
            return ended
        return {'PASS_THROUGH'}


class _Engine(_FindsTheFaceFirst):
    """The engine operators: self.plan(context) checks the input and reads the meshes (and may
    return a set to stop early), the engine runs, plan.finish writes the result.

    From the UI the faces are found first (_FindsTheFaceFirst), then the engine runs in a worker
    thread while a modal handler shows the progress and Esc cancels; elsewhere execute() runs it
    with progress_update only. Either way an error or a cancel is reported as one line and
    changes nothing."""
    bl_options = {'REGISTER', 'UNDO'}

    preset: EnumProperty(
        name="Quality",
        items=[("DEFAULT", "Preferences Default", "The preset chosen in the add-on preferences")]
        + PRESET_ITEMS, default="DEFAULT")
    formulation: EnumProperty(name="Formulation", items=FORMULATION_ITEMS, default="reduced")

    def settings(self, context):
        return workflow.clone_settings(context, self.preset, self.formulation)

    def execute(self, context):
        window_manager = context.window_manager
        window_manager.progress_begin(0.0, 1.0)
        try:
            plan = self.plan(context)
            if isinstance(plan, set):
                return plan
            run = workflow.run_engine(
                *plan.inputs, progress=lambda fraction, _: window_manager.progress_update(fraction))
            return plan.finish(run)
        except Exception as exc:
            return failed(self, exc)
        finally:
            window_manager.progress_end()

    def face_searches(self, context):
        """The parts lists whose face plan() will find (workflow.face_searches)."""
        return workflow.face_searches(context, self.use_library)

    def after_search(self, context):
        """plan() (the faces now remembered) and the engine's worker; a set if it ends here."""
        try:
            plan = self.plan(context)
            if isinstance(plan, set):
                return plan
            self._plan, self._digest = plan, workflow.mesh_digest(plan.target)
        except Exception as exc:
            return failed(self, exc)
        self._job = workflow.EngineJob(*plan.inputs).start()
        return None

    def modal_work(self, context, event):
        job = self._job
        if event.type == 'ESC':
            job.cancel()
            context.workspace.status_text_set("ExClone: cancelling at the next step...")
            return {'RUNNING_MODAL'}
        if event.type != 'TIMER':
            return {'PASS_THROUGH'}
        if not job.done:
            context.window_manager.progress_update(job.fraction)
            if not job.cancelled:
                context.workspace.status_text_set(
                    f"ExClone: {job.message} {100 * job.fraction:.0f}% (Esc cancels)")
            return {'PASS_THROUGH'}
        self._end_modal(context)
        return self._finish_job(job)

    def _finish_job(self, job):
        if job.error is not None:
            return failed(self, job.error)
        try:
            if not self._target_unchanged():
                self.report({'ERROR'}, "The target was edited or removed while the engine ran; "
                                       "nothing was written: run again")
                return {'CANCELLED'}
            return self._plan.finish(job.run)
        except Exception as exc:
            return failed(self, exc)

    def _target_unchanged(self):
        try:
            return workflow.mesh_digest(self._plan.target) == self._digest
        except ReferenceError:            # the target was deleted meanwhile
            return False


class EXCLONE_OT_clone_expressions(_Engine, bpy.types.Operator):
    """Clone the expressions (shape keys) of the source mesh, or of the built-in library, onto
    the target as new shape keys relative to its basis"""
    bl_idname = "exclone.clone_expressions"
    bl_label = "Clone Expressions"

    use_library: BoolProperty(
        name="Built-in Library",
        description="Use the bundled ICT-FaceKit ARKit expressions as the source instead of a "
                    "mesh with shape keys", default=False)
    replace_existing: BoolProperty(
        name="Replace Existing",
        description="Overwrite shape keys that already have an expression's name "
                    "(otherwise they are kept and skipped)", default=False)
    prefix: StringProperty(name="Prefix", description="Put this before every new key's name")
    only_ticked: BoolProperty(
        name="Only Ticked Expressions",
        description="Clone only the expressions ticked in the panel's list", default=False)
    parts: EnumProperty(name="Other Parts", items=PARTS_ITEMS, default="FOLLOW")

    @classmethod
    def poll(cls, context):
        return _poll_target(cls, context) and _poll_source(cls, context)

    def _wanted(self, context, names):
        if not self.only_ticked:
            return list(names)
        listed = context.scene.exclone.expressions
        if not len(listed):
            raise ExCloneError("The expression list is empty: press Refresh to fill it from the "
                               "source")
        ticked = {item.name for item in listed if item.selected}
        wanted = [name for name in names if name in ticked]
        if not wanted:
            raise ExCloneError("No expression of the source is ticked in the list")
        return wanted

    def plan(self, context):
        started = self.started()
        source, source_obj = workflow.resolve_source(context, workflow.target_object(context),
                                                     self.use_library)
        target = workflow.resolve_target(context, source, source_obj)
        face_object, head = target.face_object, target.face.head
        wanted = self._wanted(context, source.names)
        key_names = dict(zip(wanted, workflow.key_names(self.prefix, wanted)))
        existing = face_object.data.shape_keys.key_blocks.keys() \
            if face_object.data.shape_keys else []
        skipped = [] if self.replace_existing else \
            [name for name in wanted if key_names[name] in existing]
        wanted = [name for name in wanted if name not in skipped]
        if not wanted:
            self.report({'WARNING'}, f"All {len(skipped)} expressions already exist as shape "
                                     f"keys on '{face_object.name}'; enable Replace Existing "
                                     "to redo them")
            return {'CANCELLED'}

        def finish(run):
            result = run.result
            deltas = result.deltas[[result.names.index(name) for name in wanted]]
            if self.parts == 'STILL':
                deltas[:, workflow.still_parts_mask(head.mesh, result.target_landmarks)] = 0.0
            added, replaced, also_skipped = workflow.write_face_keys(
                target, [key_names[name] for name in wanted], deltas, self.replace_existing)
            followed = character_keys.follow_character(
                target, [key_names[name] for name in wanted], result,
                replace_existing=self.replace_existing, still=self.parts == 'STILL')
            measured = measures_clause(workflow.measure(face_object.name, head.mesh, result,
                                                        wanted, deltas, source))
            self.report({'INFO'}, summary(added, replaced, skipped + also_skipped,
                                          time.perf_counter() - started, result.quality)
                        + f"; {target.face.description()}"
                        + (f"; {followed}" if followed else "")
                        + (f"; {measured}" if measured else "")
                        + (" (registration reused)" if run.cached else ""))
            return {'FINISHED'}

        return Plan((source, target.face, target.landmarks, self.settings(context)), face_object,
                    finish)


class EXCLONE_OT_generate_arkit_shapes(_Engine, bpy.types.Operator):
    """One click: the built-in library cloned onto the target as Apple's 52 ARKit blend shape
    names (browInnerUp and cheekPuff combined from their halves; tongueOut opens the jaw and
    brings the tongue out); the character's eyes, brows, lashes, teeth and tongue follow"""
    bl_idname = "exclone.generate_arkit_shapes"
    bl_label = "Generate ARKit Shapes"

    replace_existing: BoolProperty(
        name="Replace Existing",
        description="Overwrite shape keys that already have an ARKit name", default=False)

    @classmethod
    def poll(cls, context):
        return _poll_target(cls, context)

    def face_searches(self, context):
        return workflow.face_searches(context, use_library=True)

    def plan(self, context):
        started = self.started()
        source = workflow.arkit_source()
        target = workflow.resolve_target(context, source, None)

        def finish(run):
            names, deltas, missing = arkit_blendshapes(run.result.names, run.result.deltas)
            added, replaced, skipped = workflow.write_face_keys(target, names, deltas,
                                                                self.replace_existing)
            followed = character_keys.follow_character(target, names, run.result,
                                                       replace_existing=self.replace_existing)
            text = summary(added, replaced, skipped, time.perf_counter() - started,
                           run.result.quality) + f"; {target.face.description()}"
            text += f"; {len(names)} of {len(ARKIT_BLENDSHAPES)} ARKit shapes" \
                + (f"; {followed}" if followed else "")
            if missing:
                text += f"; not in the library: {', '.join(missing)}"
            self.report({'INFO'}, "ARKit: " + text)
            return {'FINISHED'}

        return Plan((source, target.face, target.landmarks, self.settings(context)),
                    target.face_object, finish)


def _remove_previews():
    previews = [obj for obj in bpy.data.objects if PREVIEW_TAG in obj]
    meshes = [obj.data for obj in previews]
    bpy.data.batch_remove(previews + meshes)
    return len(previews)


class EXCLONE_OT_register_faces(_Engine, bpy.types.Operator):
    """Fit the source face onto the target with the current landmarks and report the fit error
    (the result is kept, so Clone does not redo it while nothing changes)"""
    bl_idname = "exclone.register_faces"
    bl_label = "Register"

    use_library: BoolProperty(name="Built-in Library", default=False,
                              description="Register the built-in library's face")
    preview: BoolProperty(
        name="Preview", default=True,
        description="Show the registered source as a temporary wireframe object (replaced by "
                    "the next Register, removed by Remove Preview)")

    @classmethod
    def poll(cls, context):
        return _poll_target(cls, context) and _poll_source(cls, context)

    def plan(self, context):
        started = self.started()
        source, source_obj = workflow.resolve_source(context, workflow.target_object(context),
                                                     self.use_library)
        target = workflow.resolve_target(context, source, source_obj)

        def finish(run):
            _remove_previews()
            if self.preview:
                mesh = PolyMesh(target.face.world_points(run.result.registered_source),
                                source.mesh.loop_totals, source.mesh.loop_vertices)
                preview = mesh_io.object_from_mesh(PREVIEW_NAME, mesh)   # world space
                preview[PREVIEW_TAG] = True
                preview.display_type = 'WIRE'
                preview.hide_render = True
            seconds = time.perf_counter() - started
            self.report({'INFO'}, f"Registered {source.description} onto "
                                  f"'{target.face_object.name}' ({target.face.region()}): "
                                  f"{fit_error(run.result.quality, sized=True)}, "
                                  f"{len(run.result.target_landmarks)} {run.landmark_kind} "
                                  "landmarks, " + (f"cached result ({seconds:.1f} s)"
                                                   if run.cached else f"{seconds:.1f} s"))
            return {'FINISHED'}

        return Plan((source, target.face, target.landmarks, self.settings(context), False),
                    target.face_object, finish)


class EXCLONE_OT_remove_preview(bpy.types.Operator):
    """Remove the registration preview object"""
    bl_idname = "exclone.remove_preview"
    bl_label = "Remove Preview"
    bl_options = {'REGISTER', 'UNDO'}

    @classmethod
    def poll(cls, context):
        if not any(PREVIEW_TAG in obj for obj in bpy.data.objects):
            cls.poll_message_set("There is no registration preview")
            return False
        return True

    @reporting
    def execute(self, context):
        self.report({'INFO'}, f"Removed {_remove_previews()} preview object(s)")
        return {'FINISHED'}


def _landmark_objects(context):
    """The mesh objects whose landmarks the landmark operators act on: the source object and the
    target character's meshes that hold landmarks. Auto Landmarks stores a character's on its
    face's object, so a dragged marker, an eye or the character's parent made active still edits
    them (the target itself where nothing is stored yet)."""
    target = workflow.target_object(context)
    meshes = character.family(target) if target is not None else []
    objects = [obj for obj in meshes if stored_landmarks.IDS in obj] \
        or ([target] if target is not None and target.type == 'MESH' else [])
    source = workflow.usable_source_object(context, target)
    return ([source] if source is not None and source not in objects else []) + objects


class EXCLONE_OT_auto_landmarks(_FindsTheFaceFirst, bpy.types.Operator):
    """Find the landmarks on the source and the target automatically and show them as named
    markers you can drag (then Snap Landmarks)"""
    bl_idname = "exclone.auto_landmarks"
    bl_label = "Auto Landmarks"
    bl_options = {'REGISTER', 'UNDO'}

    @classmethod
    def poll(cls, context):
        return _poll_target(cls, context)

    def face_searches(self, context):
        return workflow.face_searches(context, use_library=False, every_source=True)

    def after_search(self, context):
        return self.execute(context)

    @reporting
    def execute(self, context):
        started = self.started()
        target = workflow.target_object(context)
        source = workflow.usable_source_object(context, target)
        sources = [] if source is None else [source]
        found = {}   # every object's landmarks first: an error leaves all of them as they were
        for obj in sources:
            try:
                found[obj] = workflow.source_landmarks(obj)     # as Clone finds them
            except Exception as exc:
                return failed(self, exc, about=obj.name)
        try:        # the target is a character: its face found, landmarks on the head (as Clone)
            face_object, found_on_face = workflow.target_landmarks(context, exclude=sources)
        except Exception as exc:
            return failed(self, exc, about=target.name)
        found[face_object] = found_on_face
        for obj, landmarks in found.items():
            stored_landmarks.store(obj, landmarks, automatic=True)
        counts = ", ".join(f"{len(marks)} on '{obj.name}'" for obj, marks in found.items())
        self.report({'INFO'}, f"Landmarks placed: {counts} in {time.perf_counter() - started:.1f} s")
        return {'FINISHED'}


class _LandmarkEdit:
    bl_options = {'REGISTER', 'UNDO'}

    @classmethod
    def poll(cls, context):
        if not in_object_mode(cls, context):
            return False
        if not any(stored_landmarks.IDS in obj for obj in _landmark_objects(context)):
            cls.poll_message_set("The source and target have no landmarks: run Auto Landmarks")
            return False
        return True


class EXCLONE_OT_snap_landmarks(_LandmarkEdit, bpy.types.Operator):
    """Put every moved landmark marker on its nearest vertex and store it with the object"""
    bl_idname = "exclone.snap_landmarks"
    bl_label = "Snap Landmarks"

    @reporting
    def execute(self, context):
        snapped = {obj.name: stored_landmarks.snap(obj) for obj in _landmark_objects(context)
                   if stored_landmarks.IDS in obj}
        moved = sum(len(changed) for changed, _ in snapped.values())
        dropped = [f"{name} of '{obj}'" for obj, (_, gone) in snapped.items() for name in gone]
        detail = "; ".join(f"'{obj}': {', '.join(changed)}"
                           for obj, (changed, _) in snapped.items() if changed)
        self.report({'INFO'}, f"{moved} landmark(s) moved to a new vertex"
                              + (f" ({detail})" if detail else "")
                              + (f"; {len(dropped)} without a marker removed" if dropped else ""))
        return {'FINISHED'}


class EXCLONE_OT_mirror_landmarks(_LandmarkEdit, bpy.types.Operator):
    """Place each right-side landmark at the mirror image of its left twin (or the reverse),
    through the face's symmetry plane"""
    bl_idname = "exclone.mirror_landmarks"
    bl_label = "Mirror Landmarks"

    from_side: EnumProperty(
        name="From", items=[("left", "Left to Right", "The character's left side is copied"),
                            ("right", "Right to Left", "The character's right side is copied")],
        default="left")

    @reporting
    def execute(self, context):
        objects = [obj for obj in _landmark_objects(context) if stored_landmarks.IDS in obj]
        for obj in objects:
            stored_landmarks.checked(obj, obj.name)
        # every object's new landmarks first: an error leaves all of them as they were
        mirrored = {obj: stored_landmarks.mirrored(obj, workflow.basis_mesh(obj, obj.name),
                                                   self.from_side) for obj in objects}
        count = 0
        for obj, (landmarks, changed) in mirrored.items():
            stored_landmarks.store(obj, landmarks, automatic=False)
            count += len(changed)
        self.report({'INFO'}, f"{count} landmark(s) mirrored from the {self.from_side} side")
        return {'FINISHED'}


class EXCLONE_OT_clear_landmarks(_LandmarkEdit, bpy.types.Operator):
    """Remove the landmarks and markers of the source and target (cloning then finds automatic
    landmarks by itself)"""
    bl_idname = "exclone.clear_landmarks"
    bl_label = "Clear Landmarks"

    @reporting
    def execute(self, context):
        objects = [obj for obj in _landmark_objects(context) if stored_landmarks.IDS in obj]
        for obj in objects:
            stored_landmarks.clear(obj)
        self.report({'INFO'}, f"Landmarks removed from {', '.join(repr(o.name) for o in objects)}")
        return {'FINISHED'}


class EXCLONE_OT_refresh_expressions(bpy.types.Operator):
    """Fill the expression list from the source (ticks of names already listed are kept)"""
    bl_idname = "exclone.refresh_expressions"
    bl_label = "Refresh Expressions"
    bl_options = {'REGISTER', 'UNDO'}

    @classmethod
    def poll(cls, context):
        return _poll_source(cls, context)

    @reporting
    def execute(self, context):
        source, _ = workflow.resolve_source(context, workflow.target_object(context), False)
        listed = context.scene.exclone.expressions
        ticks = {item.name: item.selected for item in listed}
        listed.clear()
        for name in source.names:
            item = listed.add()
            item.name = name
            item.selected = ticks.get(name, True)
        self.report({'INFO'}, f"{len(source.names)} expressions from {source.description}")
        return {'FINISHED'}


def _menu_entry(self, context):
    self.layout.operator(EXCLONE_OT_clone_expressions.bl_idname)
    self.layout.operator(EXCLONE_OT_generate_arkit_shapes.bl_idname)


CLASSES = (EXCLONE_OT_clone_expressions, EXCLONE_OT_generate_arkit_shapes,
           EXCLONE_OT_register_faces, EXCLONE_OT_remove_preview, EXCLONE_OT_auto_landmarks,
           EXCLONE_OT_snap_landmarks, EXCLONE_OT_mirror_landmarks, EXCLONE_OT_clear_landmarks,
           EXCLONE_OT_refresh_expressions)
_register_classes, _unregister_classes = bpy.utils.register_classes_factory(CLASSES)


def register():
    _register_classes()
    bpy.types.VIEW3D_MT_object.append(_menu_entry)


def unregister():
    bpy.types.VIEW3D_MT_object.remove(_menu_entry)
    _unregister_classes()
