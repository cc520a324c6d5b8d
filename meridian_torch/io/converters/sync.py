"""What every converter of RGB-D recordings needs: pairing colour and depth by time, undistortion,
and the base frame placed at a camera."""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["T_BASE_OPTICAL", "associate", "undistort_maps"]

# The base frame (x forward, y left, z up) in a camera's optical frame (z forward, x right, y down):
# converters without a robot body put the base at the camera with this rotation.
T_BASE_OPTICAL = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


def associate(rgb_times: np.ndarray, depth_times: np.ndarray, max_dt_s: float) -> np.ndarray:
    """(N,) index of the depth image nearest in time to each colour image, -1 beyond `max_dt_s`.

    One-to-one: a depth image pairs with at most one colour image (the nearest), as TUM's
    associate.py does.
    """
    k = np.clip(np.searchsorted(depth_times, rgb_times), 1, len(depth_times) - 1) if len(depth_times) > 1 else None
    if k is None:
        nearest = np.zeros(len(rgb_times), dtype=np.int64)
    else:
        left_closer = np.abs(rgb_times - depth_times[k - 1]) <= np.abs(depth_times[k] - rgb_times)
        nearest = np.where(left_closer, k - 1, k)
    dt = np.abs(depth_times[nearest] - rgb_times)
    pair = np.where(dt <= max_dt_s, nearest, -1)
    # Keep only the closest colour image of every depth image.
    order = np.lexsort((dt, pair))
    taken = pair[order]
    first = np.r_[True, taken[1:] != taken[:-1]]
    keep = np.zeros(len(pair), dtype=bool)
    keep[order[first]] = True
    return np.where(keep, pair, -1)


def undistort_maps(K: np.ndarray, distortion, width: int, height: int) -> tuple[np.ndarray, np.ndarray] | None:
    """cv2.remap maps that undistort an image of this pinhole camera (same K), None without distortion."""
    distortion = np.asarray(distortion, dtype=np.float64)
    if not np.any(distortion):
        return None
    return cv2.initUndistortRectifyMap(K, distortion, None, K, (width, height), cv2.CV_32FC1)
