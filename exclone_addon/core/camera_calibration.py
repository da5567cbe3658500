"""A webcam's pinhole intrinsics from views of a printed chessboard (OpenCV's calibration), for
the tracker's camera model (docs/method.md §11)."""
import cv2
import numpy as np

from .errors import ExCloneError
from .face_models import checked_bgr
from .tracking import Camera

# OpenCV's corner finder needs a few pixels a square (its adaptive threshold fails below that).
MIN_PIXELS_PER_SQUARE = 4


def calibrate_camera(images_bgr, pattern_size=(9, 6), square_size=1.0, min_views=3, names=None):
    """Pinhole intrinsics from views of a chessboard with pattern_size inner corners.

    names: what each image is called in a message (default "image k"). Returns
    (tracking.Camera, RMS reprojection error in pixels). Lens distortion is estimated
    (k1, k2, p1, p2) so that it does not bias the focal length, but the tracker ignores it.
    """
    images = list(images_bgr)
    names = list(names) if names is not None else [f"image {k}" for k in range(len(images))]
    greys = _checked_greys(images, names, pattern_size)
    object_points = np.zeros((pattern_size[0] * pattern_size[1], 3), np.float32)
    object_points[:, :2] = np.mgrid[0:pattern_size[0], 0:pattern_size[1]].T.reshape(-1, 2) * square_size
    found = [corners for corners in (_chessboard_corners(grey, pattern_size) for grey in greys)
             if corners is not None]
    if len(found) < min_views:
        raise ExCloneError(f"a {pattern_size[0]}x{pattern_size[1]} chessboard was found in "
                           f"{len(found)} of the images; at least {min_views} views are needed")
    size = greys[0].shape[::-1]
    rms, matrix, _, _, _ = cv2.calibrateCamera([object_points] * len(found), found, size, None,
                                               None, flags=cv2.CALIB_FIX_K3)
    camera = Camera(float(matrix[0, 0]), float(matrix[1, 1]), float(matrix[0, 2]), float(matrix[1, 2]))
    return camera, float(rms)


def _checked_greys(images, names, pattern_size):
    """The images in grey; ExCloneError naming the first that is not 8-bit BGR, is too small for
    the chessboard or differs in size from the first."""
    squares = (pattern_size[0] + 1, pattern_size[1] + 1)
    least = (MIN_PIXELS_PER_SQUARE * min(squares), MIN_PIXELS_PER_SQUARE * max(squares))
    greys = []
    for image, name in zip(images, names):
        grey = cv2.cvtColor(checked_bgr(image, name), cv2.COLOR_BGR2GRAY)
        height, width = grey.shape
        if min(width, height) < least[0] or max(width, height) < least[1]:
            raise ExCloneError(f"{name} is {width}x{height} pixels; a {squares[0]}x{squares[1]}-square "
                               f"chessboard needs at least {least[1]}x{least[0]}")
        if greys and grey.shape != greys[0].shape:
            raise ExCloneError(f"{name} is {width}x{height} pixels but {names[0]} is "
                               f"{greys[0].shape[1]}x{greys[0].shape[0]}: calibration images "
                               "must all be one size")
        greys.append(grey)
    return greys


def _chessboard_corners(grey, pattern_size):
    """The inner corners, refined to sub-pixel positions, or None where the chessboard is not found."""
    ok, corners = cv2.findChessboardCorners(
        grey, pattern_size, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not ok:
        return None
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)
    return cv2.cornerSubPix(grey, corners, (5, 5), (-1, -1), criteria)
