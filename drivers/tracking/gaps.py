"""Dropouts and outliers in a tracker recording: detect, bridge the short, split at the long.

Optical trackers lose the pen when a marker is hidden (empty cells in a Motive export, a frame
flagged not tracked in NatNet), and sometimes report a wrong pose for a few frames (a marker
swap: the position jumps away and back). The reconstruction needs one
continuous path per piece, so a raw recording is cleaned before it becomes a
:class:`~recon.inputs.Recording`:

1. Samples flagged invalid or with non-finite values are dropped.
2. Outliers: a sample further than ``outlier_m`` from the moving median of its neighbours
   (a Hampel filter over ``outlier_window_s``) is a suspect; a suspect is dropped when it is
   also that far from a quadratic in time fitted to the nearest unsuspected samples on both
   sides -- a hand cannot move the pen that far and back within a few frames, but it can turn
   sharply (the apex of a fast hairpin is far from the median, yet on the curve through its
   neighbours). Orientation outliers are not detected (only quaternion sign flips, which are
   the same rotation, are made continuous).
3. Jumps: between consecutive kept samples, a speed above ``max_speed_m_s`` means the pose
   jumped (a swap that persists, or a dropout across which the pen moved): the recording is
   split there.
4. Gaps up to ``max_bridge_s`` are bridged by interpolation (PCHIP for positions, which does not
   overshoot; slerp for orientations) and the bridged samples are flagged; longer gaps split the
   recording.
5. Pieces shorter than ``min_piece_s`` are dropped.

Everything done is listed in the :class:`GapReport`.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from drivers.errors import InputFileError
from drivers.tracking.base import SampleBatch
from recon.arrays import FloatArray
from recon.inputs import Recording


@dataclass(frozen=True)
class GapParams:
    """How a raw recording is cleaned (see the module docstring).

    Attributes
    ----------
    max_bridge_s : float
        Longest dropout bridged by interpolation (default 0.1 s: a hand moves a few mm).
    max_speed_m_s : float
        Faster than this between two samples is a jump, not a hand (default 3 m/s).
    outlier_m : float
        Distance from the moving median beyond which a sample is an outlier (default 5 mm).
    outlier_window_s : float
        Width of the moving median (default 0.05 s).
    min_piece_s : float
        Pieces shorter than this are dropped (default 0.2 s).
    """

    max_bridge_s: float = 0.1
    max_speed_m_s: float = 3.0
    outlier_m: float = 5e-3
    outlier_window_s: float = 0.05
    min_piece_s: float = 0.2

    def __post_init__(self) -> None:
        for name in ("max_bridge_s", "max_speed_m_s", "outlier_m", "outlier_window_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if not self.min_piece_s >= 0:
            raise ValueError(f"min_piece_s must be >= 0, got {self.min_piece_s}")


@dataclass(frozen=True)
class GapEvent:
    """One thing done to the recording.

    Attributes
    ----------
    kind : {"bridged", "split", "outliers", "dropped_piece", "trimmed"}
    start_s, end_s : float
        Where in the recording's time it happened.
    n_samples : int
        Samples concerned (bridged, removed or dropped).
    detail : str
    """

    kind: str
    start_s: float
    end_s: float
    n_samples: int
    detail: str = ""


@dataclass(frozen=True)
class GapReport:
    """What cleaning found and did.

    Attributes
    ----------
    n_samples, n_invalid, n_outliers, n_bridged : int
        Raw samples; flagged invalid or non-finite; removed as outliers; inserted by bridging.
    events : tuple of GapEvent
    pieces : tuple of (float, float)
        Start and end time of each piece kept.
    """

    n_samples: int
    n_invalid: int
    n_outliers: int
    n_bridged: int
    events: tuple[GapEvent, ...] = field(default=())
    pieces: tuple[tuple[float, float], ...] = field(default=())

    def lines(self) -> list[str]:
        """The report for a terminal or a job result."""
        out = [
            f"{self.n_samples} samples: {self.n_invalid} lost or invalid, {self.n_outliers} "
            f"outliers removed, {self.n_bridged} bridged; {len(self.pieces)} piece(s)"
        ]
        for e in self.events:
            out.append(
                f"{e.kind} {e.start_s:.3f}-{e.end_s:.3f} s ({e.n_samples} samples)"
                + (f": {e.detail}" if e.detail else "")
            )
        return out

    def as_dict(self) -> dict[str, Any]:
        return {
            "n_samples": self.n_samples,
            "n_invalid": self.n_invalid,
            "n_outliers": self.n_outliers,
            "n_bridged": self.n_bridged,
            "pieces": [list(p) for p in self.pieces],
            "events": [e.__dict__ for e in self.events],
        }


@dataclass(frozen=True)
class CleanTrace:
    """A raw recording after cleaning.

    Attributes
    ----------
    pieces : tuple of Recording
        Continuous pieces, longest first is *not* implied: in time order.
    bridged : tuple of ndarray of shape (N_k,), bool
        Per piece, which samples were interpolated.
    report : GapReport
    """

    pieces: tuple[Recording, ...]
    bridged: tuple[np.ndarray, ...]
    report: GapReport

    def longest(self) -> int:
        """Index of the piece with the most path length."""
        lengths = [
            float(np.sum(np.linalg.norm(np.diff(p.points_m, axis=0), axis=1))) for p in self.pieces
        ]
        return int(np.argmax(lengths))


def clean_trace(raw: SampleBatch, *, params: GapParams | None = None) -> CleanTrace:
    """Turn a raw recording with dropouts into continuous pieces (module docstring).

    Parameters
    ----------
    raw : SampleBatch
        The whole recording: ``t_s`` (N,) strictly increasing, ``position_m`` (N, 3) with NaN
        where lost, ``orientation_xyzw`` (N, 4) or None, ``valid`` (N,).
    params : GapParams, optional

    Returns
    -------
    CleanTrace

    Raises
    ------
    InputFileError
        Times that do not increase, or nothing usable left (every frame lost, or only pieces
        shorter than ``min_piece_s``).
    """
    params = params or GapParams()
    t = np.asarray(raw.t_s, dtype=np.float64)
    pos = np.asarray(raw.position_m, dtype=np.float64)
    quat = None if raw.orientation_xyzw is None else np.asarray(raw.orientation_xyzw, np.float64)
    n = len(t)
    if n and np.any(np.diff(t) <= 0):
        raise InputFileError("the recording's times do not increase; sort the samples by time")
    ok = np.asarray(raw.valid, dtype=bool) & np.isfinite(pos).all(axis=1)
    if quat is not None:
        norms = np.linalg.norm(quat, axis=1)
        ok &= np.isfinite(quat).all(axis=1) & (np.abs(norms - 1.0) < 1e-2)
    n_invalid = int(n - np.count_nonzero(ok))
    events: list[GapEvent] = []
    if np.count_nonzero(ok) < 2:
        raise InputFileError(
            f"the recording has {np.count_nonzero(ok)} valid samples of {n}: the tracker lost "
            "the pen the whole time (check the rigid body or marker name, and its visibility)"
        )
    outlier = _outliers(t, pos, ok, params)
    if np.any(outlier):
        idx = np.flatnonzero(outlier)
        events.append(
            GapEvent(
                "outliers",
                float(t[idx[0]]),
                float(t[idx[-1]]),
                len(idx),
                f"further than {params.outlier_m * 1e3:.1f} mm from their neighbours' median",
            )
        )
    ok &= ~outlier
    if quat is not None:
        quat = _continuous_sign(quat, ok)
    kept = np.flatnonzero(ok)
    # Where the kept samples break: a long gap in time, or a jump in space.
    dt = np.diff(t[kept])
    step = np.linalg.norm(np.diff(pos[kept], axis=0), axis=1)
    jump = step > params.max_speed_m_s * dt
    long_gap = dt > params.max_bridge_s
    breaks = np.flatnonzero(jump | long_gap)
    for b in breaks:
        start, end = float(t[kept[b]]), float(t[kept[b + 1]])
        detail = (
            f"jump of {step[b] * 1e3:.1f} mm in {dt[b] * 1e3:.1f} ms"
            if jump[b]
            else f"tracker lost the pen for {end - start:.3f} s"
        )
        events.append(GapEvent("split", start, end, int(kept[b + 1] - kept[b] - 1), detail))
    pieces, bridged_masks, spans = [], [], []
    n_bridged = 0
    for run in np.split(kept, breaks + 1):
        if len(run) < 2 or t[run[-1]] - t[run[0]] < params.min_piece_s:
            events.append(
                GapEvent(
                    "dropped_piece",
                    float(t[run[0]]),
                    float(t[run[-1]]),
                    len(run),
                    f"shorter than {params.min_piece_s:.2f} s",
                )
            )
            continue
        lo, hi = int(run[0]), int(run[-1])
        inside = np.arange(lo, hi + 1)
        missing = ~ok[inside]
        piece_pos = pos[inside].copy()
        piece_quat = None if quat is None else quat[inside].copy()
        if np.any(missing):
            # Imported here: scipy.interpolate takes 0.3 s to import, and most traces have no
            # gap to bridge.
            from scipy.interpolate import PchipInterpolator
            from scipy.spatial.transform import Rotation, Slerp

            piece_pos[missing] = PchipInterpolator(t[run], pos[run], axis=0)(t[inside][missing])
            if piece_quat is not None and quat is not None:
                slerp = Slerp(t[run], Rotation.from_quat(quat[run]))
                piece_quat[missing] = slerp(t[inside][missing]).as_quat()
            n_bridged += int(np.count_nonzero(missing))
            for gap in _runs(missing):
                g0, g1 = inside[gap[0]], inside[gap[-1]]
                events.append(GapEvent("bridged", float(t[g0 - 1]), float(t[g1 + 1]), len(gap), ""))
        pieces.append(Recording(points_m=piece_pos, t_s=t[inside], orientations_xyzw=piece_quat))
        bridged_masks.append(missing)
        spans.append((float(t[lo]), float(t[hi])))
    lead, trail = int(kept[0]), int(n - 1 - kept[-1])
    if lead or trail:
        events.append(
            GapEvent(
                "trimmed",
                float(t[0]),
                float(t[-1]),
                lead + trail,
                f"{lead} lost samples at the start, {trail} at the end",
            )
        )
    if not pieces:
        raise InputFileError(
            f"nothing usable in the recording: every piece between dropouts is shorter than "
            f"{params.min_piece_s:.2f} s ({len(breaks)} breaks); check the tracking quality"
        )
    events.sort(key=lambda e: (e.start_s, e.kind))
    report = GapReport(
        n_samples=n,
        n_invalid=n_invalid,
        n_outliers=int(np.count_nonzero(outlier)),
        n_bridged=n_bridged,
        events=tuple(events),
        pieces=tuple(spans),
    )
    return CleanTrace(tuple(pieces), tuple(bridged_masks), report)


def _outliers(t: FloatArray, pos: FloatArray, ok: np.ndarray, params: GapParams) -> np.ndarray:
    """Samples that jump away and back (module docstring, step 2).

    Parameters
    ----------
    t : ndarray of shape (N,)
    pos : ndarray of shape (N, 3)
    ok : ndarray of shape (N,), bool
        Samples to consider (valid and finite).
    params : GapParams

    Returns
    -------
    ndarray of shape (N,), bool
    """
    idx = np.flatnonzero(ok)
    out = np.zeros(len(t), dtype=bool)
    if len(idx) < 5:
        return out
    period = float(np.median(np.diff(t[idx])))
    width = max(5, int(round(params.outlier_window_s / period)) | 1)
    from scipy.ndimage import median_filter

    median = median_filter(pos[idx], size=(width, 1), mode="nearest")
    suspect = np.linalg.norm(pos[idx] - median, axis=1) > params.outlier_m
    if not np.any(suspect):
        return out
    # Second opinion for the few suspects: the curve through the unsuspected samples nearby.
    # Fitting only to unsuspected samples keeps a run of swapped frames from vouching for itself.
    clear = np.flatnonzero(~suspect)
    reach_s = 2.0 * params.outlier_window_s
    for k in np.flatnonzero(suspect):
        at = np.searchsorted(clear, k)
        before, after = clear[max(0, at - _FIT_SIDE) : at], clear[at : at + _FIT_SIDE]
        before = before[t[idx[k]] - t[idx[before]] <= reach_s]
        after = after[t[idx[after]] - t[idx[k]] <= reach_s]
        if len(before) < 2 or len(after) < 2:
            out[idx[k]] = True  # nothing to vouch for it on one side: keep the median's verdict
            continue
        near = np.concatenate((before, after))
        dt = t[idx[near]] - t[idx[k]]
        basis = np.stack((np.ones_like(dt), dt, dt * dt), axis=1)
        coef, *_ = np.linalg.lstsq(basis, pos[idx[near]], rcond=None)
        out[idx[k]] = np.linalg.norm(pos[idx[k]] - coef[0]) > params.outlier_m
    return out


#: Unsuspected samples per side in the second-opinion fit of :func:`_outliers`.
_FIT_SIDE = 4


def _continuous_sign(quat: FloatArray, ok: np.ndarray) -> FloatArray:
    """Flip quaternions into one hemisphere along the recording (q and -q are one rotation),
    so interpolation and smoothing do not take the long way round."""
    quat = quat.copy()
    idx = np.flatnonzero(ok)
    for prev, cur in itertools.pairwise(idx):
        if np.dot(quat[prev], quat[cur]) < 0:
            quat[cur] = -quat[cur]
    return quat


def _runs(mask: np.ndarray) -> list[np.ndarray]:
    """Index runs where ``mask`` is True."""
    idx = np.flatnonzero(mask)
    if len(idx) == 0:
        return []
    return np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1)


def apply_tip_offset(raw: SampleBatch, tip_offset_m: FloatArray) -> SampleBatch:
    """Move each sample from the rigid body's origin to the pen's tip.

    Parameters
    ----------
    raw : SampleBatch
        Rigid-body positions and orientations (the orientation is required).
    tip_offset_m : ndarray of shape (3,)
        The tip in the rigid-body frame (from a pivot calibration).

    Raises
    ------
    ValueError
        No orientations, or a bad offset.
    """
    offset = np.asarray(tip_offset_m, dtype=np.float64)
    if offset.shape != (3,) or not np.all(np.isfinite(offset)):
        raise ValueError(f"tip_offset_m must be 3 finite numbers, got {tip_offset_m!r}")
    if raw.orientation_xyzw is None:
        raise ValueError(
            "a tip offset needs the rigid body's orientation; this recording has positions only"
        )
    quat = np.asarray(raw.orientation_xyzw, dtype=np.float64)
    finite = np.isfinite(quat).all(axis=1) & (np.linalg.norm(quat, axis=1) > 0.5)
    tip = np.full_like(np.asarray(raw.position_m, dtype=np.float64), np.nan)
    from scipy.spatial.transform import Rotation

    tip[finite] = raw.position_m[finite] + Rotation.from_quat(quat[finite]).apply(offset)
    return SampleBatch(
        t_s=raw.t_s,
        position_m=tip,
        orientation_xyzw=raw.orientation_xyzw,
        valid=np.asarray(raw.valid, dtype=bool) & finite,
    )
