"""The avatar a take drives: the active mesh checked, the shape keys it drives read, and its
core.retarget.AvatarRig (the tracker's points located on it) kept in a small cache."""
from collections import OrderedDict

from ..core.errors import ExCloneError
from ..core.library import ARKIT_BLENDSHAPES, ARKIT_SPLIT
from ..core.retarget import AvatarRig
from . import mesh_io, workflow

ARKIT_NAMES = frozenset(ARKIT_BLENDSHAPES) | {half for pair in ARKIT_SPLIT.values() for half in pair}
RIG_CACHE_SIZE = 2

_rigs = OrderedDict()


def checked_avatar(obj):
    if obj is None:
        raise ExCloneError("Nothing active: make the avatar head (a mesh with shape keys) the "
                           "active object")
    if obj.type != 'MESH':
        raise ExCloneError(f"'{obj.name}' is not a mesh: the avatar must be a mesh with shape keys")
    if not workflow.has_shape_keys(obj):
        raise ExCloneError(f"'{obj.name}' has no shape keys besides the basis: add expressions "
                           "first (e.g. Generate ARKit Shapes)")
    return obj


def avatar_keys(obj, key_set):
    """(names, deltas) of the shape keys a take drives: every non-basis key, or the ARKit ones."""
    names, deltas = mesh_io.shape_keys_from_object(checked_avatar(obj), what="avatar")
    if key_set == 'ARKIT':
        rows = [i for i, name in enumerate(names) if name in ARKIT_NAMES]
        if not rows:
            raise ExCloneError(f"'{obj.name}' has no shape keys with ARKit names (e.g. jawOpen, "
                               "eyeBlink_L): choose All Shape Keys")
        names, deltas = [names[i] for i in rows], deltas[rows]
    return names, deltas


def avatar_rig(obj, key_set, progress=None):
    """The avatar's AvatarRig, from a small cache: locating the tracker's face on the avatar is a
    registration (seconds), redone only when the mesh or its keys change."""
    names, deltas = avatar_keys(obj, key_set)
    mesh = workflow.basis_mesh(obj, "avatar")
    key = workflow.digest(mesh.vertices, mesh.loop_totals, mesh.loop_vertices, deltas, names)
    if key in _rigs:
        _rigs.move_to_end(key)
        return _rigs[key]
    try:
        rig = AvatarRig.from_arrays(mesh.vertices, mesh.triangles(), deltas, names,
                                    progress=progress)
    except ExCloneError as exc:
        raise ExCloneError(f"'{obj.name}': the tracker's face does not register onto this "
                           f"avatar ({exc})") from exc
    workflow.remember(_rigs, key, rig, RIG_CACHE_SIZE)
    return rig
