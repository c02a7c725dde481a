"""Splitting a resampled path into segments at its corners (Algorithm 1, second step).

Each segment is reconstructed on its own, so a polynomial never has to bend around a corner and
corners stay sharp. Where the corners are is decided in :mod:`recon.corners`.
"""

from __future__ import annotations

import itertools

import numpy as np


def split_at(n_points: int, corners: np.ndarray) -> list[tuple[int, int]]:
    """Segments ``[start, stop)`` between corners; neighbours share the corner point.

    Parameters
    ----------
    n_points : int
    corners : ndarray of int
        Sorted corner indices, each in ``(0, n_points - 1)``.

    Returns
    -------
    list of (start, stop)
    """
    bounds = [0, *[int(c) for c in corners if 0 < c < n_points - 1], n_points - 1]
    return [(a, b + 1) for a, b in itertools.pairwise(bounds)]
