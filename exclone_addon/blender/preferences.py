"""Add-on preferences: defaults that apply to every file."""
import bpy
from bpy.props import EnumProperty, IntProperty

from .properties import PRESET_ITEMS

# The add-on's top-level package: "exclone_addon" from the repository, "bl_ext.<repo>.exclone"
# when installed as an extension. Blender finds the preferences by this name.
ADDON_PACKAGE = __package__.rpartition(".")[0]
FALLBACK_PRESET = "balanced"


class EXCLONE_AP_preferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_PACKAGE

    default_preset: EnumProperty(
        name="Default Quality", items=PRESET_ITEMS, default=FALLBACK_PRESET,
        description="Registration preset used unless a scene or an operator chooses another")
    camera_index: IntProperty(
        name="Webcam", min=0, max=63, default=0,
        description="Index of the camera for Drive from Webcam (0 = the system's first camera)")

    def draw(self, context):
        layout = self.layout
        layout.prop(self, "default_preset")
        layout.prop(self, "camera_index")


def get(context):
    """The add-on's preferences, or None where the add-on was registered without being enabled
    through Blender's add-on system (e.g. exclone_addon.register() in a script)."""
    addon = context.preferences.addons.get(ADDON_PACKAGE)
    return addon.preferences if addon is not None else None


def default_preset(context):
    prefs = get(context)
    return prefs.default_preset if prefs is not None else FALLBACK_PRESET


def camera_index(context):
    """The webcam chosen in the preferences (0, the system's first camera, when not enabled)."""
    prefs = get(context)
    return prefs.camera_index if prefs is not None else 0


def register():
    bpy.utils.register_class(EXCLONE_AP_preferences)


def unregister():
    bpy.utils.unregister_class(EXCLONE_AP_preferences)
