"""Textbook reference math for tests, written independently of sefa's own code."""

import numpy as np


def matrix(p: np.ndarray) -> np.ndarray:
    """A pose [x y z qx qy qz qw] as a homogeneous 4x4 matrix."""
    x, y, z, w = p[3:] / np.linalg.norm(p[3:])
    m = np.eye(4)
    m[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    m[:3, 3] = p[:3]
    return m
