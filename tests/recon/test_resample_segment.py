"""Resampling and splitting at corners against analytic paths (corners: test_corners.py)."""

import numpy as np
import pytest

from recon.errors import DegenerateInputError
from recon.resample import resample_equidistant
from recon.segment import split_at


def test_resampled_points_are_equidistant_and_keep_the_ends():
    rng = np.random.default_rng(0)
    # A polyline with uneven steps (a hand slows down and speeds up).
    s = np.cumsum(rng.uniform(0.0001, 0.0009, 400))
    points = np.column_stack([s, np.sin(s * 20) * 0.01, np.zeros_like(s)])
    out = resample_equidistant(points, spacing_m=0.001)
    steps = np.linalg.norm(np.diff(out.points_m, axis=0), axis=1)
    # Chords of a curve are slightly shorter than the arc: equal within the curvature's effect.
    assert np.ptp(steps) < 2e-6
    assert steps.max() <= 0.001 + 1e-12
    np.testing.assert_allclose(out.points_m[0], points[0])
    np.testing.assert_allclose(out.points_m[-1], points[-1])


def test_duplicates_are_dropped_and_times_follow_arc_length():
    points = np.array([[0, 0, 0], [0, 0, 0], [0.01, 0, 0], [0.01, 0, 0], [0.02, 0, 0.0]])
    t = np.array([0.0, 0.1, 0.2, 0.3, 0.4])
    out = resample_equidistant(points, spacing_m=0.005, t_s=t)
    assert out.n_duplicates == 2
    np.testing.assert_allclose(out.points_m[:, 0], np.linspace(0, 0.02, 5))
    # Repeated positions are dropped with their times: the first of each run is kept.
    np.testing.assert_allclose(out.t_s, [0.0, 0.1, 0.2, 0.3, 0.4])


@pytest.mark.parametrize(
    "points",
    [np.zeros((5, 3)), np.array([[0, 0, 0], [0.0008, 0, 0]])],
    ids=["no-motion", "shorter-than-two-steps"],
)
def test_degenerate_paths_are_refused(points):
    with pytest.raises(DegenerateInputError):
        resample_equidistant(points, spacing_m=0.001)


def test_bad_arguments_raise_value_error():
    with pytest.raises(ValueError):
        resample_equidistant(np.zeros((5, 2)), spacing_m=0.001)
    with pytest.raises(ValueError):
        resample_equidistant(np.zeros((5, 3)), spacing_m=0.0)


def test_segments_share_their_corner_point():
    assert split_at(10, np.array([4])) == [(0, 5), (4, 10)]
    assert split_at(10, np.array([], dtype=int)) == [(0, 10)]
