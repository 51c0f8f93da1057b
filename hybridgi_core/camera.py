"""The camera's world position from its view matrix (world -> camera, column vectors): the one
place every part that needs it (the open space's viewpoint, the filters' grazing-angle stretch,
the G-buffer's view directions) reads it from."""

from __future__ import annotations

import numpy as np


def camera_position(view) -> np.ndarray:
    """(3,) float64 world position of the camera of `view` ((4, 4) or 16 values)."""
    return np.linalg.inv(np.asarray(view, np.float64).reshape(4, 4))[:3, 3]
