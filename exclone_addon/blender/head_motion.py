"""The head rotation a take drives: the object or pose bone that follows the tracked head."""
import bpy
from mathutils import Matrix, Quaternion

from ..core.errors import ExCloneError


class HeadTarget:
    """The object or pose bone that follows the head, in quaternion rotation mode.

    The tracker's head rotation is in world axes for something facing -Y; it is turned into the
    holder's own parent space (for a bone: its rest orientation in the armature, parent bones'
    poses aside) and applied on top of the rotation the holder had when the take started."""

    def __init__(self, owner, pose_bone=None):
        self.owner, self.holder = owner, pose_bone or owner
        # Blender converts the current rotation when the mode changes: the pose stays as it is.
        self.holder.rotation_mode = 'QUATERNION'
        self.rest = self.holder.rotation_quaternion.copy()
        if pose_bone is None:
            parent_space = owner.parent.matrix_world @ owner.matrix_parent_inverse \
                if owner.parent is not None else Matrix.Identity(4)
        else:
            parent_space = owner.matrix_world @ pose_bone.bone.matrix_local
        self.space = parent_space.to_quaternion()
        self.path = "rotation_quaternion"

    def apply(self, head_rotation):
        """head_rotation: a scipy Rotation in Blender's world axes (core.session's)."""
        x, y, z, w = head_rotation.as_quat()
        world = Quaternion((w, x, y, z))
        local = self.space.inverted() @ world @ self.space
        self.holder.rotation_quaternion = local @ self.rest

    def keyframe(self, frame):
        self.holder.keyframe_insert(self.path, frame=frame)


def head_holder(kind, avatar, armature_name, bone_name):
    """(owner, pose bone or None) that the head rotation goes onto, or None; checks only."""
    if kind == 'NONE':
        return None
    if kind == 'OBJECT':
        return avatar, None
    armature = bpy.data.objects.get(armature_name) if armature_name else None
    if armature is None or armature.type != 'ARMATURE':
        raise ExCloneError("Head rotation onto a bone: choose an armature" if not armature_name
                           else f"'{armature_name}' is not an armature in this file")
    bone = armature.pose.bones.get(bone_name)
    if bone is None:
        raise ExCloneError(f"Armature '{armature.name}' has no bone '{bone_name}'")
    return armature, bone
