"""The character's other objects get the face's keys (docs/method.md §9).

After Clone or Generate ARKit Shapes writes keys on the face object, the character's other mesh
objects (eyes, eyebrows, eyelashes, teeth, tongue) get the same-named keys, moved by the rules of
core/followers.py (computed in world space, written in each object's own coordinates), and each
follower key's value is driven by the face key's value, so one slider moves the whole face. Every
object ExClone gives keys lists them in its MADE property, so Remove ExClone Keys takes away
exactly those keys and their drivers.
"""
import bpy
import numpy as np

from ..core import followers
from ..core.cloning import found_landmarks
from ..core.errors import ExCloneError
from ..core.mesh import PolyMesh, diagonal
from ..core.reports import listed
from . import character, mesh_io
from .reporting import in_object_mode, reporting

MADE = "exclone_keys"            # object property: the names of the shape keys ExClone made
MADE_BASIS = "exclone_basis"     # object property: ExClone added its reference key too


# An object larger than half the solved skin (its bounding-box diagonal) is no part of a face
# (a body, clothes, a second head): eyes, brows, lashes, teeth and tongue are far smaller.
FOLLOWER_SIZE = 0.5


def skin_points(skin_vertices, skin_triangles, names, ids):
    """{name: position} of the face's points: the landmarks (names, vertex ids of the skin) if
    they are named ones, else the skin's automatic landmarks (landmarks placed by hand).
    ExCloneError if the skin's face cannot be found."""
    if not set(followers.FACE_POINTS) <= set(names):
        names, ids = found_landmarks(PolyMesh.from_faces(skin_vertices, skin_triangles.tolist()),
                                     "face")
    return dict(zip(names, np.asarray(skin_vertices)[np.asarray(ids, dtype=np.int64)]))


def follow_face(face_obj, names, skin, skin_deltas, points, objects, *, replace_existing=False):
    """Give the objects (the character's others) the face object's keys `names`, moved as they
    follow its skin, each key's value driven by the face's key of that name.

    skin: (vertices, triangles) of the solved skin in world space, skin_deltas (E, n, 3) its
    world-space displacements, points its named points ({name: (3,)}, skin_points). Returns
    [(object name, kinds, key count)] of the objects that got keys."""
    face = followers.face_from_points(*skin, points)
    objects = [obj for obj in objects if obj.library is None and obj.data.library is None]
    meshes = [tuple(character.world_mesh(obj)) for obj in objects]
    small = [diagonal(v) < FOLLOWER_SIZE * face.skin.diagonal for v, _ in meshes]
    objects = [obj for obj, keep in zip(objects, small) if keep]
    meshes = [mesh for mesh, keep in zip(meshes, small) if keep]
    done = []
    for obj, following in zip(objects, followers.follow(face, skin_deltas, names, meshes)):
        moving = following.moving_keys(names, face.span)
        if not moving:
            continue
        rows = [names.index(name) for name in moving]
        _write(obj, moving, character.local_deltas(obj, following.deltas[rows]), replace_existing)
        _drive(obj, face_obj, moving)
        done.append((obj.name, following.kinds(), len(moving)))
    mark(face_obj, names)
    return done


def follow_character(target, names, result, *, replace_existing=False, still=False):
    """Clone's and Generate ARKit's step for the character's other objects, after the face
    object got its keys `names`: follow_face with the solved head region of the face object as
    the skin, its motion read back from those keys (world space). target: the operators' target
    (face_object, others(), face.head: the head region's vertex ids); result: the engine's
    CloneResult (landmarks in the head's numbering); still: the other objects keep still (the
    face's keys are only recorded for Remove ExClone Keys). Returns the report's clause: what
    each object got, or why none did."""
    mark(target.face_object, names)
    objects = target.others()
    if not objects or still:
        return ""
    face_obj, head = target.face_object, target.face.head
    world = character.world_mesh(face_obj)
    inside = np.zeros(len(world.vertices), dtype=bool)
    inside[head.vertex_ids] = True
    skin = (world.vertices, world.triangles[inside[world.triangles].all(axis=1)])
    keyed, local = mesh_io.shape_keys_from_object(face_obj, face_obj.name)
    deltas = local[[keyed.index(name) for name in names]] @ character.linear_part(face_obj).T
    try:
        points = skin_points(*skin, result.landmark_names, head.own_ids(result.target_landmarks))
        done = follow_face(face_obj, names, skin, deltas, points, objects,
                           replace_existing=replace_existing)
    except ExCloneError as exc:
        return f"other objects kept still ({exc})"
    clause = summary(done) if done else "other objects kept still (none at the face)"
    if any(name.endswith("tongueOut") for name in names) \
            and not any("tongue" in kinds for _, kinds, _ in done):
        clause += "; tongueOut opens the jaw only (no tongue object found)"
    return clause


def mark(obj, names):
    """Record that ExClone made the keys `names` on obj (Remove ExClone Keys takes them)."""
    obj[MADE] = sorted(set(obj.get(MADE, [])) | set(names))


def _write(obj, names, deltas, replace_existing):
    if obj.data.shape_keys is None:
        obj[MADE_BASIS] = True
    mesh_io.write_shape_keys(obj, names, deltas, replace_existing=replace_existing)
    mark(obj, names)


def _drive(obj, face_obj, names):
    """Each of obj's keys `names` takes its value from the face object's key of that name."""
    keys = obj.data.shape_keys
    for name in names:
        path = f'key_blocks["{name}"].value'
        keys.driver_remove(path)
        driver = keys.driver_add(path).driver
        driver.type = 'AVERAGE'
        variable = driver.variables.new()
        variable.name = "face"
        variable.type = 'SINGLE_PROP'
        variable.targets[0].id_type = 'KEY'
        variable.targets[0].id = face_obj.data.shape_keys
        variable.targets[0].data_path = path


def summary(done):
    """One clause per group of objects: 'Eye_L, Eye_R: 4 eye keys; Teeth: 10 mouth keys'."""
    groups = {}
    for name, kinds, count in done:
        groups.setdefault((tuple(kinds), count), []).append(name)
    return "; ".join(f"{listed(names, most=4)}: {count} {'/'.join(kinds)} keys"
                     for (kinds, count), names in groups.items())


def remove_keys(objects):
    """Remove the shape keys ExClone made on the objects (and the drivers on them), and the
    reference key where ExClone added it and nothing else is left. Returns the keys removed."""
    removed = 0
    for obj in objects:
        keys = obj.data.shape_keys if obj.type == 'MESH' else None
        if MADE not in obj or keys is None:
            continue
        for name in obj[MADE]:
            block = keys.key_blocks.get(name)
            if block is None or block == keys.reference_key:
                continue
            keys.driver_remove(f'key_blocks["{name}"].value')
            obj.shape_key_remove(block)
            removed += 1
        if obj.get(MADE_BASIS) and len(keys.key_blocks) == 1:
            obj.shape_key_remove(keys.reference_key)
        for prop in (MADE, MADE_BASIS):
            obj.pop(prop, None)
    return removed


class EXCLONE_OT_remove_keys(bpy.types.Operator):
    """Remove the shape keys ExClone made on the active object and the rest of its character
    (eyes, teeth, ...), with their drivers; keys of your own stay"""
    bl_idname = "exclone.remove_keys"
    bl_label = "Remove ExClone Keys"
    bl_options = {'REGISTER', 'UNDO'}

    @classmethod
    def poll(cls, context):
        if not in_object_mode(cls, context):
            return False
        obj = context.active_object
        if obj is None or obj.type != 'MESH':
            cls.poll_message_set("Make the character's face object the active object")
            return False
        if not any(MADE in other for other in _character(context)):
            cls.poll_message_set(f"ExClone made no keys on '{obj.name}' or its character")
            return False
        return True

    @reporting
    def execute(self, context):
        objects = _character(context)
        touched = [other.name for other in objects if MADE in other]
        removed = remove_keys(objects)
        self.report({'INFO'}, f"Removed {removed} ExClone shape keys from "
                              f"{listed(touched, most=6)}")
        return {'FINISHED'}


def _character(context):
    """The active object's character (blender/character.py: its hierarchy, or the selection)."""
    return character.character_objects(context.active_object, context.selected_objects)


CLASSES = (EXCLONE_OT_remove_keys,)
register, unregister = bpy.utils.register_classes_factory(CLASSES)
