"""core.capture: frames from a video file, a folder of images, a camera index; clear errors."""
import cv2
import numpy as np
import pytest

from exclone_addon.core.capture import ImageSource, VideoSource, open_source
from exclone_addon.core.errors import ExCloneError


def numbered_frames(count, size=(64, 48)):
    """Frames whose mean grey level encodes their index (survives lossy video compression)."""
    return [np.full((size[1], size[0], 3), 20 + 20 * k, np.uint8) for k in range(count)]


def test_video_file_frames_in_order_with_timestamps(tmp_path):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (64, 48))
    assert writer.isOpened()
    for frame in numbered_frames(6):
        writer.write(frame)
    writer.release()
    with open_source(str(path)) as source:
        assert isinstance(source, VideoSource) and not source.is_live
        assert source.frame_rate == pytest.approx(25.0)
        assert source.frame_size == (64, 48)
        assert source.description == "video clip.avi (6 frames, 25 fps)"
        frames = list(source)
    assert [f.index for f in frames] == list(range(6))
    assert [f.name for f in frames] == [f"frame {k} of clip.avi" for k in range(6)]
    np.testing.assert_allclose([f.timestamp for f in frames], np.arange(6) / 25.0)
    np.testing.assert_allclose([f.image.mean() for f in frames], 20 + 20 * np.arange(6), atol=2)
    assert all(f.image.dtype == np.uint8 and f.image.shape == (48, 64, 3) for f in frames)


def test_folder_of_images_sorted_by_name(tmp_path):
    frames = numbered_frames(3)
    for k, name in enumerate(["b.png", "c.jpg", "a.bmp"]):
        cv2.imwrite(str(tmp_path / name), frames[k])
    (tmp_path / "notes.txt").write_text("not an image")
    with open_source(tmp_path, frame_rate=10) as source:
        assert isinstance(source, ImageSource)
        assert source.description == f"3 images in {tmp_path}"
        assert source.frame_rate == 10.0 and source.frame_size == (64, 48)
        read = list(source)
        assert source.read() is None
    # a.bmp (frame 2), b.png (frame 0), c.jpg (frame 1)
    np.testing.assert_allclose([f.image.mean() for f in read], [60, 20, 40], atol=2)
    np.testing.assert_allclose([f.timestamp for f in read], [0.0, 0.1, 0.2])
    assert [f.name for f in read] == ["image a.bmp", "image b.png", "image c.jpg"]
    with open_source(str(tmp_path / "b.png")) as single:
        assert single.description == "image b.png" and len(list(single)) == 1


def test_bad_sources_are_one_line_errors(tmp_path):
    with pytest.raises(ExCloneError, match="not found"):
        open_source(tmp_path / "missing.mp4")
    with pytest.raises(ExCloneError, match="holds no images"):
        open_source(tmp_path)
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"this is not a video" * 10)
    with pytest.raises(ExCloneError, match="not a readable video"):
        open_source(junk)
    broken = tmp_path / "images"
    broken.mkdir()
    cv2.imwrite(str(broken / "a.png"), numbered_frames(1)[0])
    (broken / "b.png").write_bytes(b"not a png")
    with open_source(broken) as source:
        source.read()
        with pytest.raises(ExCloneError, match="^image b.png is unreadable$"):
            source.read()
    # this machine has no camera; an index far beyond any real one is missing everywhere
    for spec in (63, "63"):
        with pytest.raises(ExCloneError, match="no camera at index 63"):
            open_source(spec)
    for spec in (tmp_path / "missing.mp4", tmp_path, junk, 63):
        with pytest.raises(ExCloneError) as info:
            open_source(spec)
        assert "\n" not in str(info.value)
