"""Array helpers shared by the core's data: the float array type, read-only copies and
piece labels.

Conventions of all the core's data (docs/architecture.md): SI units (m, rad, s); a transform
``T_a_b`` is a 4x4 homogeneous matrix mapping points of frame ``b`` into frame ``a``;
quaternions are scalar-last ``(x, y, z, w)`` where a field says ``xyzw``. Arrays held by the
dataclasses are made read-only (:func:`frozen_array`) so a result cannot be changed behind the
back of whoever stored it.
"""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, DTypeLike, NDArray

FloatArray = NDArray[np.float64]


def frozen_array(
    values: ArrayLike, *, dtype: DTypeLike = np.float64, shape_tail: tuple[int, ...] = (), name: str
) -> NDArray[Any]:
    """Copy ``values`` into a read-only array, checking its trailing shape and finiteness.

    Parameters
    ----------
    values : array_like
        The data.
    dtype : numpy dtype
        Target dtype.
    shape_tail : tuple of int
        Required trailing dimensions, e.g. ``(3,)`` for an ``(N, 3)`` array.
    name : str
        Field name used in error messages.

    Raises
    ------
    ValueError
        Wrong shape or non-finite floating-point values.
    """
    arr = np.array(values, dtype=dtype, copy=True)
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
        want = "(N, " + ", ".join(map(str, shape_tail)) + ")" if shape_tail else "(N,)"
        raise ValueError(f"{name} must have shape {want}, got {arr.shape}")
    if np.issubdtype(arr.dtype, np.floating) and not np.all(np.isfinite(arr)):
        bad = int(np.count_nonzero(~np.isfinite(arr).reshape(len(arr), -1).all(axis=1)))
        raise ValueError(f"{name} has {bad} rows with NaN or infinite values; remove or fill them")
    arr.setflags(write=False)
    return arr


def piece_labels(values: ArrayLike | None, n: int, *, name: str = "piece") -> NDArray[np.int64]:
    """Check per-point piece labels: 0, 1, ... in order, each piece at least two points long.

    Parameters
    ----------
    values : array_like of shape (n,), or None
        None: one piece (all zeros).
    n : int
        Number of points.

    Raises
    ------
    ValueError
        Wrong length, labels that do not start at 0 and step by 0 or 1, a piece of one point.
    """
    if values is None:
        arr = np.zeros(n, dtype=np.int64)
        arr.setflags(write=False)
        return arr
    arr = frozen_array(values, dtype=np.int64, name=name)
    if len(arr) != n:
        raise ValueError(f"{name} has {len(arr)} values for {n} points")
    if n and (arr[0] != 0 or np.any((np.diff(arr) != 0) & (np.diff(arr) != 1))):
        raise ValueError(f"{name} must count pieces in order: 0, 0, ..., 1, 1, ...")
    if n and np.min(np.bincount(arr)) < 2:
        raise ValueError(f"every {name} needs at least two points")
    return arr


def piece_slices(piece: NDArray[np.int64]) -> list[slice]:
    """The index range of each piece, in order (``piece`` as checked by :func:`piece_labels`)."""
    starts = np.r_[0, np.flatnonzero(np.diff(piece)) + 1, len(piece)]
    return [slice(int(a), int(b)) for a, b in itertools.pairwise(starts)]
