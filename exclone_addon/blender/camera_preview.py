"""The camera preview of a running take: the frame downscaled, with the tracked landmarks drawn in
LANDMARK_COLOUR, in the image datablock PREVIEW_IMAGE, which a gpu draw handler shows in the 3D
viewports' corner while a take runs in a window."""
import bpy
import cv2
import numpy as np

PREVIEW_IMAGE = "ExClone Camera"
PREVIEW_WIDTH = 320
LANDMARK_COLOUR = (0, 255, 0)          # RGB: pure green is rare in camera images


def preview_pixels(image_bgr, landmarks=None):
    """The frame at PREVIEW_WIDTH pixels wide with the landmarks as 2x2 dots, as Blender's image
    pixels (float RGBA, bottom row first). No bpy: a take's worker thread prepares them, so the
    main thread only copies them in (show_preview)."""
    height, width = image_bgr.shape[:2]
    scale = PREVIEW_WIDTH / width
    size = (PREVIEW_WIDTH, max(1, round(height * scale)))
    rgb = cv2.cvtColor(cv2.resize(image_bgr, size, interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2RGB)
    if landmarks is not None:
        points = np.rint((np.asarray(landmarks)[:, :2] + 0.5) * scale - 0.5).astype(int)
        for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
            x = np.clip(points[:, 0] + dx, 0, size[0] - 1)
            y = np.clip(points[:, 1] + dy, 0, size[1] - 1)
            rgb[y, x] = LANDMARK_COLOUR
    rgba = np.ones((size[1], size[0], 4), dtype=np.float32)
    rgba[..., :3] = rgb[::-1] / 255.0          # Blender's images start at the bottom row
    return rgba


def show_preview(rgba):
    """preview_pixels' result into the PREVIEW_IMAGE datablock (made or resized as needed)."""
    size = (rgba.shape[1], rgba.shape[0])
    image = bpy.data.images.get(PREVIEW_IMAGE)
    if image is None:
        image = bpy.data.images.new(PREVIEW_IMAGE, size[0], size[1])
    elif tuple(image.size) != size:
        image.scale(*size)
    image.pixels.foreach_set(rgba.ravel())
    image.update()
    return image


def show_overlay(take):
    """Draws the preview and `take`'s status in every 3D viewport until hide_overlay(handle)."""
    return bpy.types.SpaceView3D.draw_handler_add(_draw_overlay, (take,), 'WINDOW', 'POST_PIXEL')


def hide_overlay(handle):
    bpy.types.SpaceView3D.draw_handler_remove(handle, 'WINDOW')


def _draw_overlay(take):
    """The preview image in the region's bottom-right corner, with the take's status above it."""
    # imported only when drawing: background Blender has no gpu to draw with
    import blf
    import gpu
    from gpu_extras.presets import draw_texture_2d

    image = bpy.data.images.get(PREVIEW_IMAGE)
    if image is None:
        return
    region = bpy.context.region
    width, height = image.size
    x, y = region.width - width - 20, 20
    draw_texture_2d(gpu.texture.from_image(image), (x, y), width, height)
    blf.position(0, x, y + height + 8, 0)
    blf.size(0, 13)
    blf.draw(0, f"ExClone: {take.status}")
