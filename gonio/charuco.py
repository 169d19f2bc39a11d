"""ChArUco board facts shared by the reduction's and the simulator's board tables.

Both ``[board]`` tables (``capture.reduction_config.BoardSection`` and the scene's
``simulator.scene.Board``) describe an OpenCV ChArUco board; what OpenCV cannot build
sensibly is refused in one place for both (the simulator may not import ``capture``).
"""

from __future__ import annotations

__all__ = ["board_markers_problem"]


def board_markers_problem(squares_x: int, squares_y: int, dictionary: str) -> str | None:
    """Why a ChArUco board cannot be made from its dictionary, or None when it can.

    A board of ``squares_x * squares_y // 2`` markers needs that many distinct IDs.  OpenCV
    builds a larger one anyway (repeating IDs, which no detector can tell apart), and
    takes minutes over a huge one: 100000 x 7 squares stalled the reduction on every frame
    instead of being refused.

    Parameters
    ----------
    squares_x, squares_y
        Chessboard squares along the board's columns and rows.
    dictionary
        A known ``cv2.aruco`` predefined dictionary name (checked before).

    Returns
    -------
    str or None
        The sentence for the user (the board, its marker count, the dictionary's size).
    """
    import cv2

    needed = squares_x * squares_y // 2
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    held = int(d.bytesList.shape[0])
    if needed <= held:
        return None
    return (
        f"a {squares_x} x {squares_y} ChArUco board has {needed} markers, more than the "
        f"{held} of {dictionary}: use fewer squares or a larger dictionary"
    )
