"""Types of the compiled kernels (recon/_kernels.c); recon/kernels.py is what to import.

Every array argument is a C-contiguous buffer of the dtype its docstring names (float64, int64,
int32 or uint8); outputs are written in place.
"""

from typing_extensions import Buffer

def grid_nearest(
    points: Buffer,
    order: Buffer,
    cell_keys: Buffer,
    cell_starts: Buffer,
    origin: Buffer,
    cell_m: float,
    dims: Buffer,
    queries: Buffer,
    k: int,
    radius: float,
    out_distance: Buffer,
    out_index: Buffer,
    n_points: int,
    /,
) -> None: ...
def grid_ball_sums(
    points: Buffer,
    order: Buffer,
    cell_keys: Buffer,
    cell_starts: Buffer,
    origin: Buffer,
    cell_m: float,
    dims: Buffer,
    queries: Buffer,
    k: int,
    radius: float,
    columns: Buffer,
    n_columns: int,
    out_sums: Buffer,
    out_counts: Buffer,
    /,
) -> None: ...
def csr_row_sums(
    indptr: Buffer, indices: Buffer, columns: Buffer, n_columns: int, out: Buffer, /
) -> None: ...
def hough_votes(
    x: Buffer,
    y: Buffer,
    phi: Buffer,
    weight: Buffer,
    b: int,
    k: int,
    cos_theta: Buffer,
    sin_theta: Buffer,
    step: float,
    half_window: int,
    radius_m: float,
    rho_bin_m: float,
    n_rho: int,
    out: Buffer,
    /,
) -> None: ...
def voxel_nearest_centre(
    points: Buffer, order: Buffer, keys: Buffer, origin: Buffer, scale: float, out_kept: Buffer, /
) -> tuple[int, float]: ...
