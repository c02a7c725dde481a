"""The core's inputs: a recorded trace (:class:`Recording`) and a scan (:class:`Scan`).

Units, frames and quaternion order as docs/architecture.md's conventions say; the arrays held
here are read-only (:func:`recon.arrays.frozen_array`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from recon.arrays import FloatArray, frozen_array, piece_labels, piece_slices

if TYPE_CHECKING:
    pass


@dataclass(frozen=True)
class Recording:
    """A traced path as the tracker delivered it, in the tracker frame.

    Attributes
    ----------
    points_m : ndarray of shape (N, 3), metres
        Pen-tip positions in traversal order.
    t_s : ndarray of shape (N,), seconds, or None
        Sample times, strictly increasing when given.
    orientations_xyzw : ndarray of shape (N, 4), or None
        Pen orientations as unit quaternions, scalar last.
    piece : ndarray of shape (N,), int
        Which continuous piece each sample belongs to (0, 1, ... in order): a trace split by
        long dropouts or lift-offs, kept whole. All zeros (one piece) when not given.
    """

    points_m: FloatArray
    t_s: FloatArray | None = None
    orientations_xyzw: FloatArray | None = None
    piece: NDArray[np.int64] | None = None

    def __post_init__(self) -> None:
        pts = frozen_array(self.points_m, shape_tail=(3,), name="points_m")
        object.__setattr__(self, "points_m", pts)
        object.__setattr__(self, "piece", piece_labels(self.piece, len(pts)))
        if self.t_s is not None:
            t = frozen_array(self.t_s, name="t_s")
            if len(t) != len(pts):
                raise ValueError(f"t_s has {len(t)} values for {len(pts)} points")
            if len(t) > 1 and np.any(np.diff(t) <= 0):
                raise ValueError("t_s must be strictly increasing; sort the samples by time")
            object.__setattr__(self, "t_s", t)
        if self.orientations_xyzw is not None:
            q = frozen_array(self.orientations_xyzw, shape_tail=(4,), name="orientations_xyzw")
            if len(q) != len(pts):
                raise ValueError(f"orientations_xyzw has {len(q)} rows for {len(pts)} points")
            norms = np.linalg.norm(q, axis=1)
            if np.any(np.abs(norms - 1.0) > 1e-3):
                raise ValueError("orientations_xyzw must be unit quaternions (x, y, z, w)")
            object.__setattr__(self, "orientations_xyzw", q)

    def __len__(self) -> int:
        return len(self.points_m)

    def _labels(self) -> NDArray[np.int64]:
        """``piece`` as ``__post_init__`` left it (labels, never None after it)."""
        assert self.piece is not None  # set by __post_init__
        return self.piece

    @property
    def n_pieces(self) -> int:
        piece = self._labels()
        return int(piece[-1]) + 1 if len(piece) else 0

    @classmethod
    def joined(cls, pieces: list[Recording]) -> Recording:
        """Pieces (in time order) as one recording that keeps them apart (``piece``)."""
        if not pieces:
            raise ValueError("no piece to join")

        def stacked(name: str) -> NDArray[Any] | None:
            values = [getattr(p, name) for p in pieces]
            return None if any(v is None for v in values) else np.concatenate(values)

        return cls(
            points_m=np.concatenate([p.points_m for p in pieces]),
            t_s=stacked("t_s"),
            orientations_xyzw=stacked("orientations_xyzw"),
            piece=np.repeat(np.arange(len(pieces)), [len(p) for p in pieces]),
        )

    def pieces(self) -> list[Recording]:
        """Each piece as a recording of its own."""
        return [
            Recording(
                points_m=self.points_m[rows],
                t_s=None if self.t_s is None else self.t_s[rows],
                orientations_xyzw=None
                if self.orientations_xyzw is None
                else self.orientations_xyzw[rows],
            )
            for rows in piece_slices(self._labels())
        ]


@dataclass(frozen=True)
class Scan:
    """A point cloud of the workpiece, in the scan frame.

    Attributes
    ----------
    points_m : ndarray of shape (M, 3), metres
    normals : ndarray of shape (M, 3), or None
        Unit normals if the scanner or reader supplied them (orientation not relied upon).
    """

    points_m: FloatArray
    normals: FloatArray | None = None

    def __post_init__(self) -> None:
        pts = frozen_array(self.points_m, shape_tail=(3,), name="scan points_m")
        object.__setattr__(self, "points_m", pts)
        if self.normals is not None:
            n = frozen_array(self.normals, shape_tail=(3,), name="scan normals")
            if len(n) != len(pts):
                raise ValueError(f"scan has {len(n)} normals for {len(pts)} points")
            object.__setattr__(self, "normals", n)

    def __len__(self) -> int:
        return len(self.points_m)
