"""The batched least squares and PCA against numpy's one-at-a-time routines."""

import numpy as np
import pytest

from recon.fitting import (
    fit_linear,
    fit_linear_robust,
    poly_design,
    symmetric_eig3,
    weighted_pca,
    window_indices,
)


def test_window_indices_shift_inwards_at_the_ends():
    w = window_indices(6, 2)
    assert w.shape == (6, 5)
    assert w[0].tolist() == [0, 1, 2, 3, 4]
    assert w[3].tolist() == [1, 2, 3, 4, 5]
    assert w[5].tolist() == [1, 2, 3, 4, 5]
    assert window_indices(3, 5).shape == (3, 3)


def test_batched_pca_matches_eigh_per_neighbourhood():
    rng = np.random.default_rng(1)
    pts = rng.standard_normal((50, 30, 3)) * [5.0, 2.0, 0.5]
    weights = (rng.uniform(size=(50, 30)) > 0.2).astype(float)
    pca = weighted_pca(pts, weights)
    for b in range(50):
        sel = pts[b][weights[b] > 0]
        mean = sel.mean(axis=0)
        values, vectors = np.linalg.eigh(np.cov(sel.T, bias=True))
        np.testing.assert_allclose(pca.mean[b], mean, atol=1e-12)
        np.testing.assert_allclose(pca.variances[b], values[::-1], atol=1e-12)
        for k in range(3):  # axes up to sign
            assert abs(pca.axes[b, :, k] @ vectors[:, 2 - k]) == pytest.approx(1.0, abs=1e-9)


def test_batched_polynomial_fit_matches_polyfit():
    rng = np.random.default_rng(2)
    x = rng.uniform(-0.01, 0.01, (40, 25))
    y = 3.0 + 200.0 * x - 4000.0 * x**2 + rng.normal(0, 1e-4, x.shape)
    fit = fit_linear(poly_design(x, degree=2, scale=0.01), y, None)
    for b in range(40):
        expected = np.polyval(np.polyfit(x[b], y[b], 2), 0.003)
        got = fit.predict(poly_design(np.full(40, 0.003), degree=2, scale=0.01))[b, 0]
        assert got == pytest.approx(expected, rel=1e-9)
    # Residual standard deviation near the noise level; dof = 25 - 3.
    assert np.median(fit.rms) == pytest.approx(1e-4, rel=0.3)
    assert np.all(fit.dof == 22)


def test_leverage_is_the_variance_of_the_fitted_value():
    rng = np.random.default_rng(3)
    x = np.tile(np.linspace(-1, 1, 21), (4000, 1))
    y = rng.normal(0, 1.0, x.shape)  # pure noise of unit variance around zero
    design = poly_design(x, degree=2, scale=1.0)
    fit = fit_linear(design, y, None)
    at = poly_design(np.full(4000, 0.3), degree=2, scale=1.0)
    empirical = np.var(fit.predict(at)[:, 0])
    assert empirical == pytest.approx(fit.leverage(at)[0], rel=0.1)


def test_robust_fit_ignores_gross_outliers():
    rng = np.random.default_rng(4)
    x = np.tile(np.linspace(-1, 1, 41), (10, 1))
    y = 0.5 * x + rng.normal(0, 0.01, x.shape)
    y[:, 5] += 3.0  # a gross error in every neighbourhood
    plain = fit_linear(poly_design(x, degree=1, scale=1.0), y, None)
    robust, weights = fit_linear_robust(poly_design(x, degree=1, scale=1.0), y, None)
    assert np.all(weights[:, 5] == 0)
    assert np.all(np.abs(robust.coef[:, 1, 0] - 0.5) < 0.02)
    assert np.all(np.abs(plain.coef[:, 1, 0] - 0.5) > 0.02)


def test_underdetermined_neighbourhoods_are_flagged_not_fatal():
    x = np.array([[0.0, 1.0, 2.0, 3.0], [0.0, 1.0, 0.0, 0.0]])
    w = np.array([[1.0, 1.0, 1.0, 1.0], [1.0, 1.0, 0.0, 0.0]])  # second: 2 points for 3 coefs
    fit = fit_linear(poly_design(x, degree=2, scale=1.0), x**2, w)
    assert fit.fitted.tolist() == [True, False]


def test_closed_form_eigen_matches_eigh():
    rng = np.random.default_rng(5)
    pts = rng.standard_normal((2000, 20, 3)) * [3.0, 1.0, 0.1]
    rot = np.linalg.qr(rng.standard_normal((2000, 3, 3)))[0]
    pts = pts @ rot
    cov = np.einsum("mki,mkj->mij", pts, pts) / 20
    values, vector = symmetric_eig3(cov)
    ref_values, ref_vectors = np.linalg.eigh(cov)
    np.testing.assert_allclose(values, ref_values, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(
        np.abs(np.einsum("mi,mi->m", vector, ref_vectors[:, :, 0])), 1.0, atol=1e-8
    )
    # Degenerate cases: a multiple of the identity and a zero matrix.
    values, vector = symmetric_eig3(np.stack([np.eye(3) * 2.0, np.zeros((3, 3))]))
    np.testing.assert_allclose(values, [[2, 2, 2], [0, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(vector, axis=1), 1.0)
