import numpy as np
import pytest

from services.errors import InputError
from services.formats.board import board_to_json, load_board, parse_board


def test_chessboard_object_points_are_a_row_major_grid():
    board = parse_board('{"type": "chessboard", "inner_corners": [4, 3], "square_mm": 25}')
    points = board.object_points()
    assert board.polarity == "auto"
    assert points.shape == (12, 3)
    np.testing.assert_allclose(points[1], [25, 0, 0])
    np.testing.assert_allclose(points[4], [0, 25, 0])
    np.testing.assert_allclose(points[-1], [75, 50, 0])


def test_charuco_features_are_its_inner_corners():
    board = parse_board('{"type": "charuco", "squares": [5, 7], "square_mm": 20, "marker_mm": 15}')
    assert board.pattern_size == (4, 6)
    assert board.object_points().shape == (24, 3)
    assert board.opencv_board().getChessboardSize() == (5, 7)


def test_asymmetric_circles_follow_opencv_layout():
    board = parse_board('{"type": "circles", "grid": [4, 11], "spacing_mm": 20, "asymmetric": true}')
    points = board.object_points()
    np.testing.assert_allclose(points[:5, :2], [[0, 0], [40, 0], [80, 0], [120, 0], [20, 20]])


def test_round_trip_through_json():
    board = parse_board('{"type": "circles", "grid": [7, 5], "spacing_mm": 12.5, "polarity": "inverted"}')
    assert parse_board(board_to_json(board)) == board


@pytest.mark.parametrize(
    "text, fragment",
    [
        ('{"type": "chessboard", "inner_corners": [9, 6], "square_mm": 25, "squre": 1}', "squre"),
        ('{"type": "chessboard", "inner_corners": [1, 6], "square_mm": 25}', "inner_corners"),
        ('{"type": "chessboard", "inner_corners": [9, 6], "square_mm": -2}', "square_mm"),
        ('{"type": "chessboard", "inner_corners": [9, 6], "square_mm": 25, "polarity": "dark"}', "polarity"),
        ('{"type": "charuco", "squares": [5, 7], "square_mm": 20, "marker_mm": 25}', "smaller than square_mm"),
        ('{"type": "charuco", "squares": [5, 7], "square_mm": 20, "marker_mm": 15, "dictionary": "DICT_9X9"}',
         "unknown ArUco dictionary"),
        ('{"type": "charuco", "squares": [20, 20], "square_mm": 20, "marker_mm": 15}', "has only 100"),
        ('{"type": "hexagons"}', "type"),
    ],
)
def test_bad_specifications_are_refused_with_the_field_named(text, fragment):
    with pytest.raises(InputError, match=fragment) as error:
        parse_board(text, "board.json")
    assert str(error.value).startswith("board.json")


def test_load_board_names_a_missing_file(tmp_path):
    with pytest.raises(InputError, match="missing.json: cannot read"):
        load_board(tmp_path / "missing.json")
