"""A stand-in for Blender's UILayout, so panels' real draw code runs in background Blender."""
import bpy


class RecordingLayout:
    """Stands in for a UILayout (which only exists while Blender draws a region): the panel's
    real draw code runs on it, and every call is checked against the real RNA and recorded."""

    def __init__(self, log):
        self.log = log

    def _sub(self, *args, **kwargs):
        return RecordingLayout(self.log)

    row = column = box = split = _sub

    def label(self, text="", icon='NONE'):
        self.log.append(("label", text))

    def separator(self, **kwargs):
        pass

    def prop(self, data, name, **kwargs):
        assert name in data.bl_rna.properties, f"{data} has no property {name}"
        self.log.append(("prop", name))

    def operator(self, idname, text="", icon='NONE'):
        module, name = idname.split(".")
        op = getattr(getattr(bpy.ops, module), name)
        self.log.append(("operator", idname))
        return OperatorProperties(op.get_rna_type())

    def template_list(self, list_type, list_id, data, name, active_data, active_name, rows=5):
        assert hasattr(bpy.types, list_type)
        assert name in data.bl_rna.properties and active_name in active_data.bl_rna.properties
        self.log.append(("list", name))


class OperatorProperties:
    def __init__(self, rna):
        object.__setattr__(self, "rna", rna)

    def __setattr__(self, name, value):
        prop = self.rna.properties.get(name)
        assert prop is not None, f"{self.rna.identifier} has no property {name}"
        if prop.type == 'ENUM':
            assert value in prop.enum_items.keys(), f"{name}: {value!r} is not an option"
