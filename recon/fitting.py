"""Batched local fits: PCA of many neighbourhoods and polynomial least squares over all of them.

Every function here works on a batch of B neighbourhoods at once, each padded to K points with a
weight (0 for padding), so the reconstruction runs without a Python loop per path point.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from recon.arrays import FloatArray
from recon.kernels import gather_rows, normal_equations, residual_squares, weighted_moments


def window_indices(n_points: int, half_width: int) -> NDArray[np.int64]:
    """Index windows of ``2 * half_width + 1`` consecutive points, shifted inwards at the ends.

    Near an end the window keeps its size and slides inwards (as Savitzky-Golay filters do at
    their edges) rather than shrinking, so every fit has the same support.

    Parameters
    ----------
    n_points : int
    half_width : int

    Returns
    -------
    ndarray of shape (n_points, w), int
        ``w = min(2 * half_width + 1, n_points)``; row i holds the window of point i.
    """
    w = min(2 * half_width + 1, n_points)
    start = np.clip(np.arange(n_points) - half_width, 0, n_points - w)
    return start[:, None] + np.arange(w)[None, :]


@dataclass(frozen=True)
class PCA:
    """Principal components of a batch of neighbourhoods.

    Attributes
    ----------
    mean : ndarray of shape (B, 3)
        Centre of mass mu.
    axes : ndarray of shape (B, 3, 3)
        Columns are the principal directions, largest variance first (C = (C^x C^y C^z)).
    variances : ndarray of shape (B, 3)
        Eigenvalues of the covariance, descending.
    weight : ndarray of shape (B,)
        Sum of the weights (the point count for 0/1 weights).
    """

    mean: FloatArray
    axes: FloatArray
    variances: FloatArray
    weight: FloatArray

    def to_local(self, points: FloatArray) -> FloatArray:
        """Coordinates in the principal frame, ``C^T (p - mu)`` (Eq. 2).

        Parameters
        ----------
        points : ndarray of shape (B, 3) or (B, K, 3)
        """
        centred = points - (self.mean if points.ndim == 2 else self.mean[:, None, :])
        if points.ndim == 2:
            local: FloatArray = np.matmul(centred[:, None, :], self.axes)[:, 0]
        else:
            local = np.matmul(centred, self.axes)
        return local

    def to_world(self, local: FloatArray) -> FloatArray:
        """Inverse of :meth:`to_local` for one point per neighbourhood, shape (B, 3)."""
        world: FloatArray = self.mean + np.einsum("bij,bj->bi", self.axes, local)
        return world


def weighted_pca(points: FloatArray, weights: FloatArray | None = None) -> PCA:
    """PCA (Eq. 1) of each neighbourhood in a batch.

    Parameters
    ----------
    points : ndarray of shape (B, K, 3)
    weights : ndarray of shape (B, K), optional
        Non-negative weights; 0 marks padding. Default: all ones.

    Returns
    -------
    PCA
        Neighbourhoods with zero total weight get mean 0 and identity axes; callers check
        ``weight`` before trusting them.
    """
    points = np.asarray(points, dtype=np.float64)
    if weights is None:
        weights = np.ones(points.shape[:2])
    # One compiled pass per neighbourhood (eight times numpy's on (256, 768, 3): no (B, K, 3)
    # temporaries); the same sums in another order, so the same to rounding.
    moments = weighted_moments(points, weights)
    if moments is not None:
        total, mean, cov = moments
    else:
        total = weights.sum(axis=1)
        safe = np.where(total > 0, total, 1.0)
        # Batched matmul rather than a three-operand einsum: several times faster on (B, K, 3).
        mean = np.matmul(weights[:, None, :], points)[:, 0] / safe[:, None]
        centred = points - mean[:, None, :]
        cov = (
            np.matmul((centred * weights[..., None]).transpose(0, 2, 1), centred)
            / safe[:, None, None]
        )
    variances, vectors = np.linalg.eigh(cov)  # ascending
    return PCA(
        mean=mean,
        axes=vectors[:, :, ::-1].copy(),
        variances=np.maximum(variances[:, ::-1], 0.0),
        weight=total,
    )


@dataclass(frozen=True)
class LinearFit:
    """Weighted linear least squares ``y = A c`` solved in every neighbourhood of a batch.

    Attributes
    ----------
    coef : ndarray of shape (B, p, m)
        Coefficients for p basis functions and m outputs.
    rms : ndarray of shape (B,)
        Residual standard deviation over all outputs (dof-corrected), in the units of y.
    normal_inverse : ndarray of shape (B, p, p)
        Inverse of the weighted normal matrix ``A^T W A``, for leverages and standard errors.
    dof : ndarray of shape (B,)
        Residual degrees of freedom per output (points with weight > 0 minus p).
    """

    coef: FloatArray
    rms: FloatArray
    normal_inverse: FloatArray
    dof: FloatArray

    def predict(self, design_row: FloatArray) -> FloatArray:
        """Fitted value at one design row per neighbourhood: (B, p) -> (B, m)."""
        fitted: FloatArray = np.einsum("bp,bpm->bm", design_row, self.coef)
        return fitted

    def predict_all(self, design: FloatArray) -> FloatArray:
        """Fitted values at every point: design (B, K, p) -> (B, K, m)."""
        fitted: FloatArray = np.matmul(design, self.coef)
        return fitted

    def leverage(self, design_row: FloatArray) -> FloatArray:
        """``a^T (A^T W A)^-1 a`` (B,): variance of the fitted value per unit noise variance."""
        leverage: FloatArray = np.einsum(
            "bp,bpq,bq->b", design_row, self.normal_inverse, design_row
        )
        return leverage

    @property
    def fitted(self) -> NDArray[np.bool_]:
        """Neighbourhoods with more points than coefficients."""
        return self.dof > 0


def fit_linear(design: FloatArray, y: FloatArray, weights: FloatArray | None) -> LinearFit:
    """Solve weighted least squares in every neighbourhood at once.

    Parameters
    ----------
    design : ndarray of shape (B, K, p)
        Basis functions evaluated at each point (well scaled: values of order one).
    y : ndarray of shape (B, K) or (B, K, m)
        Ordinates; a 2-D ``y`` is one output.
    weights : ndarray of shape (B, K), optional
        Non-negative; 0 marks padding.

    Returns
    -------
    LinearFit
        A neighbourhood with fewer points than coefficients gets a tiny ridge term so the batch
        solves; its ``dof`` is <= 0 and callers treat it as unfit.
    """
    if y.ndim == 2:
        y = y[..., None]
    if weights is None:
        weights = np.ones(design.shape[:2])
    p = design.shape[2]
    # The normal equations and the residuals in compiled passes where the kernels are on (the
    # same sums in another order: the same to rounding), numpy's (B, p, K) products otherwise.
    compiled = normal_equations(design, y, weights)
    normal: FloatArray
    rhs: FloatArray
    if compiled is not None:
        normal, rhs = compiled
    else:
        weighted = (design * weights[..., None]).transpose(0, 2, 1)  # (B, p, K)
        normal = np.matmul(weighted, design)
        rhs = np.matmul(weighted, y)
    # A ridge of 1e-12 of the matrix's scale keeps an underdetermined neighbourhood (which the
    # caller rejects by its dof) from making the whole batched solve fail; on a well-posed one
    # it changes the result by about 1e-12 relative.
    trace = np.trace(normal, axis1=1, axis2=2) / p
    ridge = 1e-12 * np.where(trace > 0, trace, 1e12)  # an empty neighbourhood solves to zero
    normal_inverse = np.asarray(
        np.linalg.inv(normal + ridge[:, None, None] * np.eye(p)), dtype=np.float64
    )
    coef = normal_inverse @ rhs
    count = np.count_nonzero(weights > 0, axis=1).astype(np.float64)
    dof = count - p
    wsum = weights.sum(axis=1)
    # Weighted residual variance, normalised so 0/1 weights give the usual dof-corrected value.
    mean_w = np.where(count > 0, wsum / np.maximum(count, 1.0), 1.0)
    squares = residual_squares(design, y, weights, coef) if compiled is not None else None
    if squares is None:
        residual = y - np.matmul(design, coef)
        squares = np.einsum("bk,bkm->b", weights, residual**2)
    sq = squares / mean_w
    rms = np.sqrt(sq / np.maximum(dof * y.shape[2], 1.0))
    return LinearFit(coef=coef, rms=rms, normal_inverse=normal_inverse, dof=dof)


def fit_linear_robust(
    design: FloatArray,
    y: FloatArray,
    weights: FloatArray | None,
    *,
    rejection: float = 3.0,
    floor: float = 0.0,
    iterations: int = 2,
) -> tuple[LinearFit, FloatArray]:
    """:func:`fit_linear`, then refits without points more than ``rejection`` RMS off the fit.

    Scan-derived points come with a few gross errors (a face fit that straddled three faces, a
    stray reflection); a least-squares fit would follow them.

    Parameters
    ----------
    design, y, weights :
        As for :func:`fit_linear`.
    rejection : float
        Points whose residual exceeds ``rejection * max(rms, floor)`` get weight 0.
    floor : float
        Lower bound on the residual scale (in y's units), so an almost exact fit does not reject
        points for residuals at rounding level.
    iterations : int

    Returns
    -------
    fit : LinearFit
    weights : ndarray of shape (B, K)
        The weights of the final fit.
    """
    if y.ndim == 2:
        y = y[..., None]
    base = np.ones(design.shape[:2]) if weights is None else weights
    fit = fit_linear(design, y, base)
    current = base
    for _ in range(iterations):
        residual = np.linalg.norm(y - fit.predict_all(design), axis=2)
        scale = rejection * np.maximum(fit.rms, floor)[:, None]
        current = np.where(residual <= scale, base, 0.0)
        fit = fit_linear(design, y, current)
    return fit, current


def poly_design(x: FloatArray, *, degree: int, scale: float) -> FloatArray:
    """Powers ``(x / scale)^0 .. (x / scale)^degree`` along a new last axis.

    Dividing by the neighbourhood's size keeps the normal equations well conditioned (millimetre
    neighbourhoods in metres would square to 1e-6 and below). Built by repeated products: a
    power with an array of exponents calls ``pow`` per element, ten times slower.
    """
    u = np.asarray(x, dtype=np.float64) / scale
    powers = np.empty((*u.shape, degree + 1))
    powers[..., 0] = 1.0
    for d in range(1, degree + 1):
        np.multiply(powers[..., d - 1], u, out=powers[..., d])
    return powers


def quadric_design(u: FloatArray, v: FloatArray, *, scale: float) -> FloatArray:
    """Basis ``1, u, v, u^2, u v, v^2`` (scaled) of a height field over a local plane."""
    a, b = np.asarray(u) / scale, np.asarray(v) / scale
    return np.stack([np.ones_like(a), a, b, a * a, a * b, b * b], axis=-1)


def symmetric_eig3(cov: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Eigenvalues and the smallest eigenvector of many symmetric 3x3 matrices, in closed form.

    About five times faster than ``numpy.linalg.eigh`` on (M, 3, 3) stacks (no LAPACK call per
    matrix). Eigenvalues by the trigonometric solution of the characteristic cubic; the
    eigenvector of the smallest as the largest cross product of two rows of ``A - l_min I``,
    which is perpendicular to the other two eigenvectors. Where the two smallest eigenvalues
    (nearly) coincide the vector is any unit vector of their plane, as with ``eigh``.

    Parameters
    ----------
    cov : ndarray of shape (M, 3, 3)
        Symmetric positive semi-definite matrices.

    Returns
    -------
    values : ndarray of shape (M, 3)
        Ascending.
    smallest : ndarray of shape (M, 3)
        Unit eigenvector of ``values[:, 0]``.
    """
    a = np.asarray(cov, dtype=np.float64)
    q = np.trace(a, axis1=1, axis2=2) / 3.0
    off = a[:, 0, 1] ** 2 + a[:, 0, 2] ** 2 + a[:, 1, 2] ** 2
    diag = (a[:, 0, 0] - q) ** 2 + (a[:, 1, 1] - q) ** 2 + (a[:, 2, 2] - q) ** 2
    p = np.sqrt((diag + 2.0 * off) / 6.0)
    safe_p = np.where(p > 0, p, 1.0)
    # The diagonal shifted in place rather than by a broadcast identity matrix (an (M, 3, 3)
    # product and difference each): the same numbers, off the diagonal x - 0 is x.
    b = _minus_diagonal(a, q)
    b /= safe_p[:, None, None]
    r = np.clip(np.linalg.det(b) / 2.0, -1.0, 1.0)
    phi = np.arccos(r) / 3.0
    largest = q + 2.0 * p * np.cos(phi)
    smallest_value = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    middle = 3.0 * q - largest - smallest_value
    values = np.stack([smallest_value, middle, largest], axis=1)
    shifted = _minus_diagonal(a, smallest_value)
    # The three cross products of the rows and their lengths written out component by component,
    # in np.cross's and np.linalg.norm's order of operations (the same bits, without their
    # (M, 3, 3) stacks); the longest is taken, the first among equals as argmax would.
    rows = [shifted[:, i] for i in range(3)]
    best_vector = np.zeros((len(a), 3))
    best_length = np.full(len(a), -np.inf)
    for i, j in ((0, 1), (0, 2), (1, 2)):
        u, v = rows[i], rows[j]
        cross = np.empty((len(a), 3))
        cross[:, 0] = u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1]
        cross[:, 1] = u[:, 2] * v[:, 0] - u[:, 0] * v[:, 2]
        cross[:, 2] = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]
        squares = cross * cross
        length = np.sqrt(squares[:, 0] + squares[:, 1] + squares[:, 2])
        longer = (length > best_length) | (np.isnan(length) & ~np.isnan(best_length))
        best_vector = np.where(longer[:, None], cross, best_vector)
        best_length = np.where(longer, length, best_length)
    vector, length = best_vector, best_length
    fallback = np.tile([0.0, 0.0, 1.0], (len(a), 1))
    vector = np.where(
        length[:, None] > 1e-300, vector / np.where(length > 0, length, 1.0)[:, None], fallback
    )
    return values, vector


def _minus_diagonal(a: FloatArray, shift: FloatArray) -> FloatArray:
    """``a - shift[:, None, None] * I`` for (M, 3, 3) ``a`` and (M,) ``shift``, as a new array."""
    out = a.copy()
    for i in range(3):
        out[:, i, i] -= shift
    return out


def gather(
    values: NDArray[Any], index: NDArray[np.int64], fill_index: int | None = None
) -> FloatArray:
    """``values[index]`` where entries equal to ``fill_index`` (padding) read as zeros.

    Parameters
    ----------
    values : ndarray of shape (M, ...)
    index : ndarray of shape (B, K), int
        Indices into ``values``; ``fill_index`` (typically ``M``, as scipy's KD-tree reports
        missing neighbours) marks padding.
    """
    if fill_index is None:
        return values[index]
    compiled = gather_rows(values, index, fill_index)
    if compiled is not None:
        return compiled
    dtype = np.result_type(values.dtype, np.float64)
    missing = index == fill_index
    if len(values) == 0:
        return np.zeros((*index.shape, *values.shape[1:]), dtype=dtype)
    # Indexing with the padding sent to row 0, then zeroing it, copies only what is gathered
    # (padding ``values`` with a zero row first copied the whole array on every call).
    out = values[np.where(missing, 0, index)].astype(dtype, copy=False)
    out[missing] = 0
    return out
