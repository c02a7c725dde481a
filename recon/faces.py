"""The one face under a path point: a smooth patch of the scan grown from the points right under
it, and a quadric fitted to that patch alone.

A quadric fitted to every scan point near a path point spans whatever lies there: two faces at an
edge (it lands inside the material between them), the two walls of a slot (it lands in the gap), a
step (it lands in the air above it). So the face is selected first. It is seeded by the scan
points nearest to the path point whose normals agree with the flattest nearby voxel's, and grown
outwards in two stages: within :data:`STAGE_ONE_RADIUS_M` by the seed's plane, then over the
whole neighbourhood by the first stage's quadric. A point joins only where its height is within
three noise levels of the face so far and its normal agrees with the face's, so a wall, a step or
the far side of an edge, whose heights or normals differ, stay out.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from recon.arrays import FloatArray
from recon.fitting import fit_linear_robust, gather, quadric_design, weighted_pca
from recon.scan_model import ScanModel

#: The seed: this many dense points nearest to the path point (about 15-30 mm^2 of a face).
SEED_POINTS = 32
#: Seed points lie within this height of the face the cross-section shows under the point.
SEED_HEIGHT_M = 0.0012
#: The first stage grows the seed's plane this far.
STAGE_ONE_RADIUS_M = 0.008
#: A face may curve: the first stage allows a height of ``rho^2 / (2 R)`` off the seed's plane at
#: a distance rho, for faces of this radius of curvature and flatter.
MIN_FACE_RADIUS_M = 0.02
#: A point's normal (at a small scale, :attr:`recon.scan_model.ScanModel.fine_normals`) must be
#: within this of the face's to join it: a wall, a chamfer or the far side of an edge turn by
#: more, the noise of those normals (about 6 degrees) by less.
NORMAL_TOLERANCE_DEG = 25.0
#: Noise floor of the face's height, metres: a nearly exact face does not shut out points for
#: rounding-level residuals.
HEIGHT_FLOOR_M = 0.1e-3
#: Steps from the point straight down the seed frame's axis towards its foot on the quadric, each
#: along the quadric's normal where the last one landed.
FOOT_ITERATIONS = 2
#: The fit's evidence: the face needs this many points ...
MIN_FACE_POINTS = 24
#: ... and one of them within this distance (in the face's plane) of the path point.
MAX_SUPPORT_GAP_M = 0.002


@dataclass(frozen=True)
class FaceFit:
    """The face under each of B path points.

    Attributes
    ----------
    target_m : ndarray of shape (B, 3)
        The path point moved along the face's normal onto the fitted quadric.
    normal : ndarray of shape (B, 3)
        Unit normal of the face at the target (sign arbitrary).
    variance_m2 : ndarray of shape (B,)
        Variance of the target's height from the fit.
    count : ndarray of shape (B,), int
        Points of the face used.
    rms_m : ndarray of shape (B,)
        RMS residual of the face's points to the quadric.
    support_gap_m : ndarray of shape (B,)
        In-plane distance from the target to the nearest point of the face.
    ok : ndarray of shape (B,), bool
        Enough points, one of them near the target: the scan defines the face here.
    """

    target_m: FloatArray
    normal: FloatArray
    variance_m2: FloatArray
    count: np.ndarray
    rms_m: FloatArray
    support_gap_m: FloatArray
    ok: np.ndarray


#: Path points whose faces are fitted at once: each holds up to ``neighbours`` (a thousand) scan
#: points with their normals, local coordinates and design rows (about 20 MB for 256), so a
#: per-point stage's chunk of 2,048 points would hold about ten times that per thread.
FIT_CHUNK = 256


def fit_faces(
    centres_m: FloatArray, model: ScanModel, *, radius_m: float, neighbours: int, scale_m: float
) -> FaceFit:
    """The face under each path point (see the module docstring), :data:`FIT_CHUNK` points at a
    time (each point's fit is its own: the parts are the whole's, row for row).

    Parameters and returns as :func:`_fit_faces_part`.
    """
    centres_m = np.asarray(centres_m, dtype=np.float64)
    parts = [
        _fit_faces_part(
            centres_m[i : i + FIT_CHUNK],
            model,
            radius_m=radius_m,
            neighbours=neighbours,
            scale_m=scale_m,
        )
        for i in range(0, max(len(centres_m), 1), FIT_CHUNK)
    ]
    if len(parts) == 1:
        return parts[0]
    return FaceFit(
        **{f.name: np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(FaceFit)}
    )


def _fit_faces_part(
    centres_m: FloatArray, model: ScanModel, *, radius_m: float, neighbours: int, scale_m: float
) -> FaceFit:
    """The face under each path point (see the module docstring).

    Parameters
    ----------
    centres_m : ndarray of shape (B, 3)
        Path points (smoothed), scan frame.
    model : ScanModel
    radius_m : float
        The neighbourhood the face may grow over.
    neighbours : int
        At most this many dense points of it (the nearest).
    scale_m : float
        Abscissa scale of the quadric (conditioning).

    Returns
    -------
    FaceFit
    """
    centres_m = np.asarray(centres_m, dtype=np.float64)
    b = len(centres_m)
    dense = model.features.dense_points_m
    k = min(neighbours, len(dense))
    dist, idx = model.dense_tree.query(centres_m, k=k, distance_upper_bound=radius_m, workers=-1)
    if k == 1:
        dist, idx = dist[:, None], idx[:, None]
    present = np.isfinite(dist)
    points = gather(dense, idx, fill_index=len(dense))
    normals = gather(model.fine_normals, idx, fill_index=len(dense))

    # The face under the point: as the cross-section there shows it (its direction and where
    # it is: a step's two levels face the same way), else the flattest voxel's direction.
    reference, feet, found = model.faces_under(centres_m)
    reference = np.where(found[:, None], reference, _reference_normals(centres_m, model))
    cos_tol = np.cos(np.radians(NORMAL_TOLERANCE_DEG))
    agree = present & (np.abs(np.einsum("bki,bi->bk", normals, reference)) >= cos_tol)
    on_level = np.abs(np.einsum("bki,bi->bk", points - feet[:, None], reference))
    level = ~found[:, None] | (on_level <= SEED_HEIGHT_M)
    # Seed: the nearest points that face that way (and lie on that face).
    rank = np.cumsum(agree & level, axis=1)
    seed = agree & level & (rank <= SEED_POINTS)
    frame = weighted_pca(points, seed.astype(np.float64))
    local = frame.to_local(points)
    u, v, h = local[..., 0], local[..., 1], local[..., 2]
    rho2 = u * u + v * v
    seed_sigma = np.sqrt(np.maximum(frame.variances[:, 2], HEIGHT_FLOOR_M**2))
    stage_one = (
        agree
        & (rho2 <= STAGE_ONE_RADIUS_M**2)
        & (np.abs(h) <= 3.0 * seed_sigma[:, None] + rho2 / (2.0 * MIN_FACE_RADIUS_M))
    )
    design = quadric_design(u, v, scale=scale_m)
    fit, _ = fit_linear_robust(design, h, stage_one.astype(np.float64), floor=HEIGHT_FLOOR_M)
    residual = np.abs(h - fit.predict_all(design)[..., 0])
    tolerance = 3.0 * np.maximum(fit.rms, HEIGHT_FLOOR_M)[:, None]
    stage_two = agree & (residual <= tolerance)
    fit, weights = fit_linear_robust(design, h, stage_two.astype(np.float64), floor=HEIGHT_FLOOR_M)
    used = weights > 0

    at = frame.to_local(centres_m)
    coef = fit.coef[:, :, 0]
    # The target is the point's foot on the quadric: where the quadric's own normal through the
    # point meets it, not straight down the seed frame's axis. The seeds are the few points
    # nearest the point, and a point lifted a few millimetres off the face has them in a small
    # patch whose plane tilts by degrees in the scan's noise: straight down it, a 6 mm lift-off
    # landed 0.5-1 mm to the side (measured on the paper's Fig. 7 plate). The quadric, fitted
    # over the whole face within reach, has the face's slope.
    foot = at[:, :2].copy()
    for _ in range(FOOT_ITERATIONS):
        height = fit.predict(quadric_design(foot[:, 0], foot[:, 1], scale=scale_m))[:, 0]
        slope_u, slope_v = _quadric_slopes(coef, foot[:, 0], foot[:, 1], scale_m)
        local_normal = np.column_stack([-slope_u, -slope_v, np.ones(b)])
        local_normal /= np.linalg.norm(local_normal, axis=1)[:, None]
        on_face = np.column_stack([foot, height])
        off = np.einsum("bi,bi->b", at - on_face, local_normal)
        foot = (at - off[:, None] * local_normal)[:, :2]
    design_at = quadric_design(foot[:, 0], foot[:, 1], scale=scale_m)
    height = fit.predict(design_at)[:, 0]
    axes = frame.axes
    target = frame.to_world(np.column_stack([foot, height]))
    # The quadric's normal at the target: (-dh/du, -dh/dv, 1) in the face's frame.
    slope_u, slope_v = _quadric_slopes(coef, foot[:, 0], foot[:, 1], scale_m)
    local_normal = np.column_stack([-slope_u, -slope_v, np.ones(b)])
    local_normal /= np.linalg.norm(local_normal, axis=1)[:, None]
    normal = np.einsum("bij,bj->bi", axes, local_normal)
    count = np.count_nonzero(used, axis=1)
    gap2 = np.where(used, (u - foot[:, :1]) ** 2 + (v - foot[:, 1:2]) ** 2, np.inf).min(axis=1)
    gap = np.sqrt(gap2)
    variance = fit.rms**2 * np.minimum(fit.leverage(design_at), 1.0)
    # The face fitted is the one under the point only if it faces the way that one does: seeded
    # by a few points, the fit can grow over a neighbouring face instead (a low step's riser).
    facing = np.abs(np.einsum("bi,bi->b", normal, reference)) >= cos_tol
    ok = (fit.dof >= 4) & (count >= MIN_FACE_POINTS) & (gap <= MAX_SUPPORT_GAP_M) & facing
    return FaceFit(
        target_m=target,
        normal=normal,
        variance_m2=np.where(ok, variance, np.inf),
        count=count,
        rms_m=fit.rms,
        support_gap_m=gap,
        ok=ok,
    )


def _reference_normals(centres_m: FloatArray, model: ScanModel) -> FloatArray:
    """The normal of the flattest of the voxels nearest to each point (the face the point is
    over, not the blend of an edge nearby)."""
    coarse = model.features
    k = min(8, len(coarse.points_m))
    _, nearest = model.coarse_tree.query(centres_m, k=k, workers=-1)
    if k == 1:
        nearest = nearest[:, None]
    flattest = nearest[np.arange(len(centres_m)), np.argmin(coarse.curvature[nearest], axis=1)]
    normals: FloatArray = coarse.normals[flattest]
    return normals


def _quadric_slopes(
    coef: FloatArray, u: FloatArray, v: FloatArray, scale_m: float
) -> tuple[FloatArray, FloatArray]:
    """dh/du and dh/dv of :func:`recon.fitting.quadric_design`'s quadric at (u, v)."""
    # quadric_design: 1, u/s, v/s, (u/s)^2, (u/s)(v/s), (v/s)^2
    us, vs = u / scale_m, v / scale_m
    du = (coef[:, 1] + 2 * coef[:, 3] * us + coef[:, 4] * vs) / scale_m
    dv = (coef[:, 2] + coef[:, 4] * us + 2 * coef[:, 5] * vs) / scale_m
    return du, dv
