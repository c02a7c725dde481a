"""Several demonstrations of one path fused into one trace before it is reconstructed.

An operator's drift off the feature is slow and differs from one demonstration to the next: the
mean of three traces drifts about 1/sqrt(3) as much, and the rigid part of the drift, which no
registration to the scan can tell from a misplaced scanner, shrinks with it.

:func:`fuse_traces` resamples every trace by arc length, turns the ones traced the other way
round, aligns them along the path (each point placed at the arc length of its nearest point on
the current mean, repeated as the mean settles) and averages them point by point with weights
from each trace's own roughness. A trace that runs far from the others (another path, a
demonstration gone wrong) is left out and named. Each fused point carries its variance: the
weighted spread of the traces about it, divided by how many there are.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from recon.arrays import FloatArray
from recon.errors import DegenerateInputError
from recon.inputs import Recording
from recon.resample import resample_equidistant
from recon.results import DemonstrationReport

#: Alignment passes (project on the mean, average again).
PASSES = 3
#: A trace is an outlier when its mean distance from the others' median is more than this many
#: times the typical trace's ...
OUTLIER_FACTOR = 3.0
#: ... and more than this (traces of one path by one hand stay within a few millimetres).
OUTLIER_FLOOR_M = 0.002
#: Demonstrations whose typical distance from their median is above this are not of one path
#: (one hand's traces of one feature stay within a few millimetres of each other).
SAME_PATH_M = 0.01
#: Fused points need at least this share of the traces (used ones) at their arc length: the ends
#: are where most demonstrations start and stop, not where one overshot.
MIN_COVERAGE = 0.5
#: A trace's roughness is the RMS of its departure from a smoothing of it over this length.
ROUGHNESS_WINDOW_M = 0.008


@dataclass(frozen=True)
class FusedTrace:
    """Several traces as one.

    Attributes
    ----------
    recording : Recording
        The fused trace (tracker frame), equidistant; no times or pen orientations (traces drawn
        at different speeds have no common clock).
    variance_m2 : ndarray of shape (N,)
        Variance of each fused point's position (sum over the three axes).
    coverage : ndarray of shape (N,), int
        How many traces each fused point averages.
    traces : tuple of DemonstrationReport
        In the order given.
    """

    recording: Recording
    variance_m2: FloatArray
    coverage: NDArray[np.int64]
    traces: tuple[DemonstrationReport, ...]

    @property
    def notes(self) -> list[str]:
        """What a summary says about the fusion."""
        used = sum(t.used for t in self.traces)
        lines = [f"{used} of {len(self.traces)} demonstrations fused"]
        for k, t in enumerate(self.traces):
            if not t.used:
                lines.append(f"demonstration {k + 1} left out: {t.reason}")
            elif t.reversed:
                lines.append(f"demonstration {k + 1} was traced the other way round and turned")
        return lines


def fuse_traces(recordings: list[Recording], *, spacing_m: float) -> FusedTrace:
    """Fuse demonstrations of one path (see the module docstring).

    Parameters
    ----------
    recordings : list of Recording
        At least two, tracker frame; each may be in pieces (a dropout), which are resampled on
        their own and leave a gap that the other traces fill.
    spacing_m : float
        Resampling step of the traces and of the result.

    Returns
    -------
    FusedTrace

    Raises
    ------
    ValueError
        Fewer than two recordings, or a bad spacing.
    DegenerateInputError
        Fewer than two traces agree (after leaving out outliers), or they share no stretch.
    """
    if len(recordings) < 2:
        raise ValueError("fusing needs at least two recordings")
    if not spacing_m > 0:
        raise ValueError(f"spacing_m must be > 0, got {spacing_m}")
    pieces = [_resampled_pieces(r, spacing_m) for r in recordings]
    # The result runs the way the first demonstration does; the others are turned to match
    # when they mostly run against it where they pass it (their ends alone do not tell on a
    # loop, nor on a demonstration of part of the path).
    first = np.concatenate(pieces[0])
    flipped = [_runs_against(np.concatenate(ps), first) for ps in pieces]
    pieces = [
        [p[::-1] for p in ps[::-1]] if reverse else ps
        for ps, reverse in zip(pieces, flipped, strict=True)
    ]
    # The longest (most complete) demonstration is the first reference to align along.
    lengths = [sum(_length(p) for p in ps) for ps in pieces]
    reference = np.concatenate(pieces[int(np.argmax(lengths))])
    roughness = np.array([_roughness(ps, spacing_m) for ps in pieces])
    everyone = np.ones(len(pieces), dtype=bool)
    mean = reference
    for _ in range(PASSES):
        grid = _arc(mean)
        sampled = np.stack([_on_grid(ps, mean, grid) for ps in pieces])  # (T, G, 3), NaN gaps
        # Every pass judges every trace again: an early mean, aligned along one trace, may make
        # a good one look far.
        mean, used, offsets = _robust_mean(sampled, roughness, everyone)
        mean, keep = _covered(mean, sampled, used)
        if np.count_nonzero(keep) < 2:
            raise DegenerateInputError(
                "the demonstrations share no stretch of path: trace the same path each time"
            )
        mean = resample_equidistant(mean[keep], spacing_m=spacing_m).points_m
    grid = _arc(mean)
    sampled = np.stack([_on_grid(ps, mean, grid) for ps in pieces])
    fused, used, offsets = _robust_mean(sampled, roughness, everyone)
    variance, coverage = _variance(sampled[used], fused, roughness[used])
    reports = []
    for k in range(len(pieces)):
        reason = ""
        if not used[k]:
            reason = (
                f"it runs {offsets[k] * 1e3:.1f} mm from the others on average, more than "
                f"{OUTLIER_FACTOR:g} times the typical demonstration"
            )
        reports.append(
            DemonstrationReport(
                bool(used[k]), bool(flipped[k]), float(offsets[k]), float(roughness[k]), reason
            )
        )
    keep = _enough(coverage, used)
    return FusedTrace(
        recording=Recording(points_m=fused[keep]),
        variance_m2=variance[keep],
        coverage=coverage[keep],
        traces=tuple(reports),
    )


def _resampled_pieces(recording: Recording, spacing_m: float) -> list[FloatArray]:
    out = []
    for piece in recording.pieces():
        if len(piece) >= 2 and np.ptp(piece.points_m, axis=0).max() > 2 * spacing_m:
            out.append(resample_equidistant(piece.points_m, spacing_m=spacing_m).points_m)
    if not out:
        raise DegenerateInputError("a demonstration has no stretch longer than two steps")
    return out


def _length(points: FloatArray) -> float:
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())


def _arc(points: FloatArray) -> FloatArray:
    return np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))))


def _roughness(pieces: list[FloatArray], spacing_m: float) -> float:
    """RMS departure of a trace from its moving average over :data:`ROUGHNESS_WINDOW_M`."""
    k = max(1, int(round(ROUGHNESS_WINDOW_M / spacing_m / 2)))
    residuals = []
    for p in pieces:
        if len(p) <= 2 * k:
            continue
        kernel = np.ones(2 * k + 1) / (2 * k + 1)
        smooth = np.column_stack([np.convolve(p[:, i], kernel, mode="valid") for i in range(3)])
        residuals.append(p[k:-k] - smooth)
    if not residuals:
        return 1e-4
    r = np.concatenate(residuals)
    return max(float(np.sqrt(np.mean(np.sum(r**2, axis=1)))), 1e-6)


#: A trace's point is aligned to the nearest point of the mean within this arc-length window
#: around where its own arc length puts it: a path that crosses itself (a loop back to its
#: start) has two nearest candidates, and only one is where the trace is along the path.
ALIGN_WINDOW_M = 0.03
#: Where its own arc length puts a point is counted from the last aligned point this far back:
#: traces of one path differ in length by a percent or two (over 10 m, far more than the
#: window), and a jittery trace's arc length runs ahead of the path's.
ALIGN_BLOCK_M = 0.02


def _runs_against(trace: FloatArray, reference: FloatArray) -> bool:
    """Whether ``trace`` mostly runs the other way from ``reference`` where it passes it
    (directions compared at points every few millimetres, each with the reference's nearest)."""
    step = max(1, len(trace) // 200)
    here = trace[::step]
    if len(here) < 3 or len(reference) < 3:
        return False
    own = np.gradient(here, axis=0)
    _, nearest = cKDTree(reference).query(here)
    theirs = np.gradient(reference, axis=0)[nearest]
    return float(np.sum(np.einsum("ij,ij->i", own, theirs))) < 0.0


def _moving_average(points: FloatArray, width: int) -> FloatArray:
    """Each point averaged with its neighbours, ``width`` in all (fewer at the ends)."""
    if len(points) < width:
        return points
    kernel = np.ones(width)
    total = np.column_stack([np.convolve(points[:, i], kernel, mode="same") for i in range(3)])
    count = np.convolve(np.ones(len(points)), kernel, mode="same")
    return total / count[:, None]


def _on_grid(pieces: list[FloatArray], mean: FloatArray, grid: FloatArray) -> FloatArray:
    """A trace's positions at the mean's arc lengths ``grid`` (NaN where it has none).

    Each of its pieces starts at the point of the mean nearest to its first point (the earliest
    of the near ones, and after where the previous piece ended); then each point is placed at
    the nearest point of the mean within :data:`ALIGN_WINDOW_M` of where its arc length from the
    last aligned point (:data:`ALIGN_BLOCK_M` back) puts it. Positions in between are
    interpolated within each piece.
    """
    out = np.full((len(grid), 3), np.nan)
    spacing = grid[1] - grid[0] if len(grid) > 1 else 1.0
    half = max(1, int(np.ceil(ALIGN_WINDOW_M / spacing)))
    block = max(1, int(np.ceil(ALIGN_BLOCK_M / spacing)))
    lowest = 0
    for points in pieces:
        if lowest >= len(grid) - 1:
            break
        gaps = np.linalg.norm(mean[lowest:] - points[0], axis=1)
        anchor = lowest + int(np.flatnonzero(gaps <= gaps.min() + 2e-3)[0])
        # Arc length of the trace smoothed over a few millimetres: its jitter is not progress.
        arc = _arc(_moving_average(points, 5)) / spacing
        index = np.empty(len(points), dtype=np.int64)
        for start in range(0, len(points), block):
            rows = slice(start, min(start + block, len(points)))
            origin = anchor if start == 0 else int(index[start - 1])
            expected = np.round(origin + arc[rows] - (arc[start - 1] if start else 0.0))
            candidates = np.clip(
                expected.astype(np.int64)[:, None] + np.arange(-half, half + 1),
                lowest,
                len(grid) - 1,
            )
            distance = np.linalg.norm(mean[candidates] - points[rows, None, :], axis=2)
            index[rows] = candidates[np.arange(len(distance)), np.argmin(distance, axis=1)]
        s = grid[index]
        # Hand traces go forwards; a point projected behind its predecessor (noise at a turn)
        # keeps the order by taking the running maximum.
        s = np.maximum.accumulate(s)
        lowest = int(np.searchsorted(grid, s[-1]))
        inside = (grid >= s[0]) & (grid <= s[-1])
        if s[-1] - s[0] <= 0 or not inside.any():
            continue
        s_unique, first = np.unique(s, return_index=True)
        for axis in range(3):
            out[inside, axis] = np.interp(grid[inside], s_unique, points[first, axis])
    return out


def _robust_mean(
    sampled: FloatArray, roughness: FloatArray, used: NDArray[np.bool_]
) -> tuple[FloatArray, NDArray[np.bool_], FloatArray]:
    """Weighted mean of the used traces; outliers (far from the others' median) left out."""
    present = ~np.isnan(sampled[..., 0])
    candidates = np.where(used[:, None, None], sampled, np.nan)
    # The median where some trace is (elsewhere it stays NaN, and no distance is taken there).
    covered = present[used].any(axis=0)
    median = np.full(sampled.shape[1:], np.nan)
    median[covered] = np.nanmedian(candidates[:, covered], axis=0)
    distance = np.linalg.norm(sampled - median, axis=2)
    offsets = np.array(
        [
            np.nanmean(d[p]) if np.isfinite(d[p]).any() else np.inf
            for d, p in zip(distance, present, strict=True)
        ]
    )
    typical = np.median(offsets[used])
    out = used & ~((offsets > OUTLIER_FACTOR * typical) & (offsets > OUTLIER_FLOOR_M))
    if np.count_nonzero(out) < 2 or typical > SAME_PATH_M:
        raise DegenerateInputError(
            "fewer than two demonstrations agree with each other (they run "
            f"{typical * 1e3:.1f} mm from their median on average): trace the same path each time"
        )
    weight = np.where(out, 1.0 / roughness**2, 0.0)[:, None] * _taper(present)
    total = weight.sum(axis=0)
    mean = (
        np.einsum("tg,tgi->gi", weight, np.nan_to_num(sampled)) / np.maximum(total, 1e-300)[:, None]
    )
    mean[total == 0] = np.nan
    return mean, out, offsets


#: A trace's weight ramps up over this many grid points from where it starts, stops or has a
#: gap, so that the mean does not jump where the number of traces averaged changes.
TAPER_POINTS = 10


def _taper(present: np.ndarray) -> FloatArray:
    """Per trace and grid point: 0 where absent, rising linearly to 1 over
    :data:`TAPER_POINTS` from every end of what it covers."""
    weights = np.zeros(present.shape)
    for k, row in enumerate(present):
        # Distance (in grid points) to the nearest absent point or end, on either side.
        index = np.arange(len(row))
        absent = np.flatnonzero(~row)
        bounds = np.concatenate(([-1], absent, [len(row)]))
        left = bounds[np.searchsorted(bounds, index, side="right") - 1]
        right = bounds[np.searchsorted(bounds, index, side="left")]
        distance = np.minimum(index - left, right - index)
        weights[k] = np.where(row, np.minimum(distance / TAPER_POINTS, 1.0), 0.0)
    return weights


def _enough(coverage: np.ndarray, used: np.ndarray) -> np.ndarray:
    """Grid points covered by enough of the used traces (:data:`MIN_COVERAGE`, at least two)."""
    return coverage >= max(2, int(np.ceil(MIN_COVERAGE * np.count_nonzero(used))))


def _covered(
    mean: FloatArray, sampled: FloatArray, used: NDArray[np.bool_]
) -> tuple[FloatArray, NDArray[np.bool_]]:
    coverage = (~np.isnan(sampled[used][..., 0])).sum(axis=0)
    keep = _enough(coverage, used) & ~np.isnan(mean[:, 0])
    return mean, keep


def _variance(
    sampled: FloatArray, fused: FloatArray, roughness: FloatArray
) -> tuple[FloatArray, NDArray[np.int64]]:
    """Per fused point: the variance of the weighted mean (sum over axes), and the coverage.

    The traces' scatter about the mean estimates each one's variance there; the mean's is that
    over the (effective) number of traces, and never less than what their roughness alone gives.
    """
    present = ~np.isnan(sampled[..., 0])
    coverage = present.sum(axis=0)
    weight = (1.0 / roughness**2)[:, None] * present
    total = np.maximum(weight.sum(axis=0), 1e-300)
    scatter = (
        np.nansum(weight * np.sum((np.nan_to_num(sampled) - fused) ** 2, axis=2) * present, axis=0)
        / total
    )
    n = np.maximum(coverage, 1)
    spread = scatter * n / np.maximum(n - 1, 1) / n
    floor = 1.0 / total
    return np.maximum(spread, floor), coverage.astype(np.int64)
