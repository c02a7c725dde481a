"""Writing reconstruction results as files users open elsewhere (CSV)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from drivers.files import atomic_path
from recon.types import PointMode, Reconstruction

#: Columns after x, y, z, in order (the CSV contract of ``teachpath reconstruct``).
DIAGNOSTIC_COLUMNS = (
    "displacement_m",
    "mode",
    "segment",
    "n_path",
    "n_surface",
    "residual_path_m",
    "residual_surface_m",
    "alpha",
)


def write_reconstruction_csv(path: str | Path, recon: Reconstruction) -> None:
    """Write a reconstruction: ``x,y,z`` (metres), ``t`` if known, then per-point diagnostics.

    ``mode`` is written as a word (path, surface, edge, unchanged); NaN residuals (no such fit)
    as empty cells. The file appears only when complete.
    """
    labels = {int(m): m.label for m in PointMode}
    header = ["x", "y", "z"] + (["t"] if recon.t_s is not None else []) + list(DIAGNOSTIC_COLUMNS)

    def number(value: float) -> str:
        return "" if not np.isfinite(value) else f"{value:.9g}"

    with atomic_path(path) as tmp, tmp.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(header)
        for i in range(len(recon)):
            row = [number(v) for v in recon.points_m[i]]
            if recon.t_s is not None:
                row.append(number(recon.t_s[i]))
            row += [
                number(recon.displacement_m[i]),
                labels[int(recon.mode[i])],
                str(int(recon.segment[i])),
                str(int(recon.n_path[i])),
                str(int(recon.n_surface[i])),
                number(recon.residual_path_m[i]),
                number(recon.residual_surface_m[i]),
                number(recon.alpha[i]),
            ]
            writer.writerow(row)
