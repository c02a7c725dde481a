"""The one ``.npz`` codec: named arrays to a file and back, never a pickle.

Every array file of the project goes through here: the artifacts' arrays
(:func:`service.parsing.save_arrays`), what an isolated child hands back
(:mod:`drivers.isolation`). Which arrays an artifact holds is its codec's business
(:mod:`service.artifacts`); this module only writes and reads them.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import IO

import numpy as np
from numpy.typing import ArrayLike, NDArray

NpzArrays = dict[str, NDArray[np.generic]]


def write_npz(target: str | Path | IO[bytes], arrays: Mapping[str, ArrayLike]) -> None:
    """Write ``arrays`` uncompressed to ``target`` (a path or a binary file open for writing).

    Parameters
    ----------
    target : str, Path or binary file
    arrays : mapping of str to array-like
        Each value as ``np.asarray`` makes it; any shape and numeric, boolean or string dtype.

    Raises
    ------
    TypeError
        A value is an array of Python objects: it could only be stored as a pickle, which
        :func:`read_npz` never loads.
    """
    converted: dict[str, NDArray[np.generic]] = {}
    for key, value in arrays.items():
        array = np.asarray(value)
        if array.dtype.hasobject:
            raise TypeError(f"array {key!r} holds Python objects, which an .npz cannot carry")
        converted[str(key)] = array
    np.savez(target, **converted)  # type: ignore[arg-type]  # numpy's stub types allow_pickle


def read_npz(source: str | Path | IO[bytes]) -> NpzArrays:
    """The arrays of an ``.npz`` (written by :func:`write_npz`), loaded whole; a member that is a
    pickle is refused (``ValueError`` from numpy), never unpickled.

    Parameters
    ----------
    source : str, Path or binary file

    Returns
    -------
    dict of str to ndarray
    """
    with np.load(source, allow_pickle=False) as data:
        return {key: data[key] for key in data.files}
