"""Reading back the keyframes an operator wrote (bpy 5.0: through the action slot's channel bag)."""
from bpy_extras import anim_utils


def keyframes(animated):
    """{data path: [(frame, value), ...]} of an ID's action, through its slot's channel bag."""
    animation = animated.animation_data
    if animation is None or animation.action is None:
        return {}
    bag = anim_utils.action_get_channelbag_for_slot(animation.action, animation.action_slot)
    return {curve.data_path: [tuple(point.co) for point in curve.keyframe_points]
            for curve in bag.fcurves} if bag is not None else {}
