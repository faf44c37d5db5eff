import cv2
import numpy as np
import pytest

from services.errors import InputError
from services.formats.images import read_frame, read_frame_stack, write_png


@pytest.mark.parametrize("suffix, dtype", [(".png", np.uint8), (".png", np.uint16), (".bmp", np.uint8),
                                           (".tiff", np.uint16)])
def test_bit_depth_is_kept(tmp_path, suffix, dtype):
    image = (np.arange(12 * 10).reshape(10, 12) * 97 % np.iinfo(dtype).max).astype(dtype)
    cv2.imwrite(str(tmp_path / f"f{suffix}"), image)
    frame = read_frame(tmp_path / f"f{suffix}")
    assert frame.dtype == dtype
    np.testing.assert_array_equal(frame, image)


def test_colour_becomes_grey(tmp_path):
    write_png(tmp_path / "c.png", np.full((4, 5, 3), 200, np.uint8))
    assert read_frame(tmp_path / "c.png").shape == (4, 5)


def test_errors_name_the_file(tmp_path):
    with pytest.raises(InputError, match="missing"):
        read_frame(tmp_path / "nope.png")
    (tmp_path / "broken.png").write_bytes(b"\x89PNG garbage")
    with pytest.raises(InputError, match="broken.png"):
        read_frame(tmp_path / "broken.png")
    write_png(tmp_path / "a.png", np.zeros((4, 5), np.uint8))
    write_png(tmp_path / "b.png", np.zeros((4, 6), np.uint8))
    with pytest.raises(InputError, match="b.png: frame is 6x4 but a.png is 5x4"):
        read_frame_stack([tmp_path / "a.png", tmp_path / "b.png"])
