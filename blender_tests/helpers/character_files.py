"""The shared character files (.blend appended, .glb or .fbx imported) in the current scene."""
import bpy


def load_into_scene(path):
    """Every object of the file in the current scene, transforms evaluated: {name: object}."""
    if path.suffix == ".blend":
        with bpy.data.libraries.load(str(path), link=False) as (source, loaded):
            loaded.objects = list(source.objects)
        for obj in loaded.objects:
            bpy.context.scene.collection.objects.link(obj)
    elif path.suffix == ".glb":
        bpy.ops.import_scene.gltf(filepath=str(path))
    else:
        bpy.ops.import_scene.fbx(filepath=str(path))
    bpy.context.view_layer.update()
    return {obj.name: obj for obj in bpy.context.scene.objects}
