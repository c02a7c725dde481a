"""The result CSVs (reconstruction, trajectory), written as one formatted block, against the
row-by-row writers they replaced."""

from __future__ import annotations

import csv
import io

import numpy as np
import pytest

from drivers.export import DIAGNOSTIC_COLUMNS, QUATERNION_COLUMNS, reconstruction_csv_text
from recon.results import PointMode, PointReason


def _arrays(
    n: int, *, times: bool, quaternions: bool, uncertainty: bool, reason: bool = True, seed: int = 0
):
    rng = np.random.default_rng(seed)
    arrays = {
        "points_m": rng.normal(scale=0.3, size=(n, 3)),
        "displacement_m": rng.exponential(1e-3, n),
        "mode": rng.integers(0, 4, n),
        "segment": rng.integers(0, 3, n),
        "n_path": rng.integers(0, 30, n),
        "n_surface": rng.integers(0, 1000, n),
        "residual_path_m": rng.exponential(1e-4, n),
        "residual_surface_m": rng.exponential(1e-4, n),
        "alpha": rng.uniform(0, 1, n),
        "piece": rng.integers(0, 2, n),
    }
    # No such fit: NaN; the writer must never print nan or inf.
    arrays["residual_surface_m"][::7] = np.nan
    arrays["residual_path_m"][3::11] = np.inf
    arrays["alpha"][5::13] = -np.inf
    if times:
        arrays["t_s"] = np.cumsum(rng.uniform(0.001, 0.01, n))
    if quaternions:
        q = rng.normal(size=(n, 4))
        arrays["orientations_xyzw"] = q / np.linalg.norm(q, axis=1, keepdims=True)
    if uncertainty:
        arrays["uncertainty_m"] = rng.exponential(3e-4, n)
    if reason:
        arrays["reason"] = rng.integers(0, len(PointReason), n).astype(np.int8)
    # Values that print differently in %g than in repr: tiny, huge, negative zero, integral.
    arrays["points_m"][0] = (1e-12, -0.0, 12345.0)
    return arrays


def _row_by_row(arrays: dict) -> str:
    """The straightforward writer: csv.writer, one f-string per number."""
    labels = {int(m): m.label for m in PointMode}
    reasons = {int(r): r.label for r in PointReason}
    n = len(arrays["points_m"])
    t, q = arrays.get("t_s"), arrays.get("orientations_xyzw")
    unc = arrays.get("uncertainty_m", np.full(n, np.nan))

    def number(value):
        return "" if not np.isfinite(value) else f"{value:.9g}"

    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(
        ["x", "y", "z"]
        + (["t"] if t is not None else [])
        + (list(QUATERNION_COLUMNS) if q is not None else [])
        + list(DIAGNOSTIC_COLUMNS)
    )
    for i in range(n):
        row = [number(v) for v in arrays["points_m"][i]]
        row += [number(t[i])] if t is not None else []
        row += [number(v) for v in q[i]] if q is not None else []
        row += [
            number(arrays["displacement_m"][i]),
            labels[int(arrays["mode"][i])],
            str(int(arrays["segment"][i])),
            str(int(arrays["n_path"][i])),
            str(int(arrays["n_surface"][i])),
            number(arrays["residual_path_m"][i]),
            number(arrays["residual_surface_m"][i]),
            number(arrays["alpha"][i]),
            str(int(arrays["piece"][i])),
            number(unc[i]),
            reasons[int(arrays["reason"][i])] if "reason" in arrays else "",
        ]
        writer.writerow(row)
    return buffer.getvalue()


@pytest.mark.parametrize("times", [False, True])
@pytest.mark.parametrize("quaternions", [False, True])
@pytest.mark.parametrize("uncertainty", [False, True])
@pytest.mark.parametrize("reason", [False, True])
def test_the_block_writer_writes_what_a_row_by_row_writer_writes(
    times, quaternions, uncertainty, reason
):
    arrays = _arrays(
        500, times=times, quaternions=quaternions, uncertainty=uncertainty, reason=reason
    )
    assert reconstruction_csv_text(arrays) == _row_by_row(arrays)


def test_an_empty_reconstruction_is_a_header_only():
    arrays = {
        key: value[:0]
        for key, value in _arrays(3, times=False, quaternions=False, uncertainty=True).items()
    }
    assert reconstruction_csv_text(arrays) == _row_by_row(arrays)
    assert reconstruction_csv_text(arrays).count("\n") == 1


def test_the_trajectory_csv_is_what_numpy_savetxt_wrote_and_reads_back(tmp_path):
    from drivers.export import (
        META_PREFIX,
        TRAJECTORY_COLUMNS,
        read_trajectory_csv,
        trajectory_csv_text,
        write_trajectory_csv,
    )
    from recon.paths import Phase
    from tests.motion_fixtures import line_plan

    trajectory = line_plan().trajectory  # every phase, from the arm's home
    text = trajectory_csv_text(trajectory, meta={"source": "test"})
    # The row-by-row writer it replaced: numpy.savetxt, then the phase's word.
    numbers = np.column_stack(
        [trajectory.t_s, trajectory.q_rad, trajectory.tcp_m, trajectory.tcp_rotvec]
    )
    body = io.StringIO()
    np.savetxt(body, numbers, delimiter=",", fmt="%.10g")
    labels = [p.label for p in Phase]
    rows = [
        f"{line},{labels[phase]}"
        for line, phase in zip(body.getvalue().splitlines(), trajectory.phases, strict=True)
    ]
    head, columns, *data = text.splitlines()
    assert head.startswith(META_PREFIX)
    assert columns == ",".join((*TRAJECTORY_COLUMNS, "phase"))
    assert data == rows
    path = tmp_path / "trajectory.csv"
    write_trajectory_csv(path, trajectory, meta={"source": "test"})
    back = read_trajectory_csv(path, robot=trajectory.robot).trajectory
    np.testing.assert_allclose(back.q_rad, trajectory.q_rad, rtol=0, atol=1e-9)
