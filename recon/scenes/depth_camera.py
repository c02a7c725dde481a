"""A depth camera simulated on a triangle mesh: what a structured-light or stereo camera held by a
person would give of a real part.

Rays of a pinhole image are cast at the mesh with Open3D's ``RaycastingScene``. What makes the
cloud look like a real camera's rather than a sampled CAD surface:

* **noise along the ray that grows with depth**: a stereo camera matches disparity to a fraction
  of a pixel, so the depth error is ``z^2 / (f b)`` times the disparity error (0.6 mm at 0.45 m
  by default, as a RealSense D4xx-class camera at close range);
* **quantisation**: the disparity comes in steps of a sixteenth of a pixel, so depth comes in
  steps (0.4 mm at 0.45 m);
* **dropouts at grazing angles**: a surface seen nearly edge-on returns nothing (none beyond
  :attr:`DepthCamera.grazing_limit_deg`, fewer and fewer from 15 degrees before it);
* **dropouts at depth edges**: the pixels either side of a jump in depth are lost (the matcher's
  window straddles two surfaces), which leaves a gap along every silhouette;
* **views that do not fit perfectly**: each view of a multi-view scan is merged with a small
  registration error of its own.

Everything is in the frame of the mesh (the tracker frame of a scene); the caller moves the fused
cloud to a scan frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from recon.arrays import FloatArray

if TYPE_CHECKING:
    import open3d as o3d


def cpu_tensor(array: np.ndarray, dtype: str = "float32") -> o3d.core.Tensor:
    """``array`` as an Open3D tensor on the CPU, of ``dtype`` (``"float32"`` or ``"uint32"``):
    what the raycasting scene takes (a copy; Open3D's stubs want the dtype and device named)."""
    import open3d as o3d

    values = np.ascontiguousarray(array, dtype=dtype)
    return o3d.core.Tensor(values, getattr(o3d.core, dtype), o3d.core.Device("CPU:0"))


MM = 1e-3
#: The depth the depth-edge threshold is given at.
REFERENCE_DEPTH_M = 0.45


@dataclass(frozen=True)
class DepthCamera:
    """A pinhole depth camera and its error model.

    Attributes
    ----------
    width_px, height_px : int
        Image size.
    focal_px : float
        Focal length in pixels (600 px over 640 px: a 56-degree horizontal field of view).
    baseline_m : float
        Stereo baseline; with the focal length it converts disparity to depth.
    disparity_sigma_px : float
        Standard deviation of the matched disparity, pixels (sets the depth noise:
        0.6 mm at 0.45 m with the defaults).
    disparity_step_px : float
        The disparity's quantum (sets the depth steps).
    grazing_limit_deg : float
        No return from a surface whose normal is farther than this from the ray; returns thin
        out linearly over the 15 degrees before it.
    depth_edge_m : float
        Neighbouring pixels whose depths differ by more than this (at 0.45 m; it scales with
        depth squared, as the matcher's uncertainty does) are both dropped.
    view_shift_m, view_angle_deg : float
        Standard deviation of each view's registration error when views are merged.
    """

    width_px: int = 640
    height_px: int = 480
    focal_px: float = 600.0
    baseline_m: float = 0.055
    disparity_sigma_px: float = 0.098
    disparity_step_px: float = 1.0 / 16.0
    grazing_limit_deg: float = 78.0
    depth_edge_m: float = 3 * MM
    view_shift_m: float = 0.05 * MM
    view_angle_deg: float = 0.01

    def depth_sigma_m(self, depth_m: FloatArray | float) -> FloatArray | float:
        """The depth noise (1 sigma) at a depth, metres."""
        return (
            np.asarray(depth_m) ** 2 / (self.focal_px * self.baseline_m) * self.disparity_sigma_px
        )


@dataclass(frozen=True)
class View:
    """Where the camera stands and what it looks at (mesh frame).

    Attributes
    ----------
    eye_m : ndarray of shape (3,)
    target_m : ndarray of shape (3,)
    up : ndarray of shape (3,)
        Roughly the image's up direction.
    """

    eye_m: FloatArray
    target_m: FloatArray
    up: FloatArray


def hand_held_views(
    targets_m: FloatArray,
    rng: np.random.Generator,
    *,
    distance_m: float = 0.45,
    facings: FloatArray | None = None,
    elevation_deg: tuple[float, float] = (35.0, 65.0),
) -> list[View]:
    """Viewpoints as a person scanning a part on a table would take them: from above the table
    (z up), one view pointed at each place of interest, from the side it faces.

    Parameters
    ----------
    targets_m : ndarray of shape (V, 3)
        What each view is pointed at (1 to 3 views).
    rng : numpy.random.Generator
    distance_m : float
        Camera to target (about 0.45 m: a depth camera's sweet spot at close range).
    facings : ndarray of shape (V, 3), optional
        The direction the feature faces at each target (e.g. the outward bisector of an edge):
        the camera stands on that side, give or take 20 degrees of azimuth. Random where not
        given or vertical.
    elevation_deg : (float, float)
        Range of the camera's elevation above the horizontal.

    Returns
    -------
    list of View
    """
    targets_m = np.atleast_2d(np.asarray(targets_m, dtype=np.float64))
    if not 1 <= len(targets_m) <= 3:
        raise ValueError(f"1 to 3 views, got {len(targets_m)}")
    views = []
    for k, target in enumerate(targets_m):
        heading = None
        if facings is not None:
            facing = np.asarray(facings[k], dtype=np.float64)
            if np.linalg.norm(facing[:2]) > 0.3 * np.linalg.norm(facing):
                heading = float(np.arctan2(facing[1], facing[0]))
        if heading is None:
            heading = float(rng.uniform(0.0, 2.0 * np.pi))
        azimuth = heading + np.radians(rng.uniform(-20.0, 20.0))
        elevation = np.radians(rng.uniform(*elevation_deg))
        direction = np.array(
            [
                np.cos(elevation) * np.cos(azimuth),
                np.cos(elevation) * np.sin(azimuth),
                np.sin(elevation),
            ]
        )
        views.append(View(target + distance_m * direction, target, np.array([0.0, 0.0, 1.0])))
    return views


def _camera_axes(view: View) -> FloatArray:
    """Rows: the camera's x (right), y (down), z (forward) in the mesh frame."""
    forward = view.target_m - view.eye_m
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, view.up)
    if np.linalg.norm(right) < 1e-9:  # looking straight along up
        right = np.cross(forward, [1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return np.stack([right, down, forward])


@dataclass(frozen=True)
class SimulatedScan:
    """What a simulated depth camera returned, with what it truly hit.

    Attributes
    ----------
    points_m : ndarray of shape (M, 3)
        The returns as the camera gives them (noise, quantisation, the views' merge errors).
    surface_m : ndarray of shape (M, 3)
        Where each return's ray truly met the mesh.
    triangle : ndarray of shape (M,), int
        The mesh triangle it met.
    """

    points_m: FloatArray
    surface_m: FloatArray
    triangle: np.ndarray


def scan_mesh(
    vertices_m: FloatArray,
    triangles: np.ndarray,
    views: list[View],
    rng: np.random.Generator,
    *,
    camera: DepthCamera | None = None,
) -> SimulatedScan:
    """Scan a mesh from several views and merge the views (mesh frame).

    Parameters
    ----------
    vertices_m : ndarray of shape (V, 3), metres
    triangles : ndarray of shape (F, 3), int
    views : list of View
    rng : numpy.random.Generator
    camera : DepthCamera, optional

    Returns
    -------
    SimulatedScan
        Every view's returns, each view moved by its own small registration error.
    """
    import open3d as o3d  # the simulator's only user of Open3D's ray casting

    camera = camera or DepthCamera()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        cpu_tensor(vertices_m),
        cpu_tensor(triangles, "uint32"),
    )
    clouds, surfaces, hit_triangles = [], [], []
    for view in views:
        points, surface, triangle = _scan_view(scene, view, camera, rng)
        error = Rotation.from_rotvec(
            np.radians(camera.view_angle_deg) * rng.standard_normal(3)
        ).as_matrix()
        shift = camera.view_shift_m * rng.standard_normal(3)
        centre = view.target_m
        clouds.append((points - centre) @ error.T + centre + shift)
        surfaces.append(surface)
        hit_triangles.append(triangle)
    if not clouds:
        return SimulatedScan(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64))
    return SimulatedScan(
        np.concatenate(clouds), np.concatenate(surfaces), np.concatenate(hit_triangles)
    )


def _scan_view(
    scene: o3d.t.geometry.RaycastingScene,
    view: View,
    camera: DepthCamera,
    rng: np.random.Generator,
) -> tuple[FloatArray, FloatArray, NDArray[np.int64]]:
    """One view's returns (mesh frame) with the camera's errors (see the module docstring), the
    true hit points and the triangles hit."""

    h, w, f = camera.height_px, camera.width_px, camera.focal_px
    axes = _camera_axes(view)
    u, v = np.meshgrid(np.arange(w) + 0.5 - w / 2, np.arange(h) + 0.5 - h / 2)
    # Ray through each pixel centre, in the mesh frame: (u / f, v / f, 1) in camera axes.
    local = np.stack([u / f, v / f, np.ones_like(u)], axis=-1)
    directions = local @ axes
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    rays = np.concatenate([np.broadcast_to(view.eye_m, directions.shape), directions], axis=-1)
    hit = scene.cast_rays(cpu_tensor(rays))
    distance = hit["t_hit"].numpy().astype(np.float64)
    normals = hit["primitive_normals"].numpy().astype(np.float64)
    triangle = hit["primitive_ids"].numpy().astype(np.int64)
    valid = np.isfinite(distance)
    # Depth along the optical axis, as the camera measures it.
    cos_axis = directions @ axes[2]
    depth = np.where(valid, distance * cos_axis, np.nan)

    # Grazing angles: fewer returns as the surface turns away, none past the limit.
    incidence = np.degrees(np.arccos(np.clip(np.abs(np.sum(normals * directions, -1)), 0, 1)))
    limit = camera.grazing_limit_deg
    keep_probability = np.clip((limit - incidence) / 15.0, 0.0, 1.0)
    valid &= rng.uniform(size=valid.shape) < keep_probability

    # Depth edges: both sides of a jump lose their pixels (a miss counts as infinitely far, so
    # a silhouette against the background loses its rim too).
    filled = np.where(np.isfinite(depth), depth, np.inf)
    edge = np.zeros_like(valid)
    for first, second, pair in (
        (filled[:-1], filled[1:], (np.s_[:-1], np.s_[1:])),
        (filled[:, :-1], filled[:, 1:], (np.s_[:, :-1], np.s_[:, 1:])),
    ):
        with np.errstate(invalid="ignore"):
            near = np.minimum(first, second)
            big = np.abs(second - first) > camera.depth_edge_m * (near / REFERENCE_DEPTH_M) ** 2
        edge[pair[0]] |= big
        edge[pair[1]] |= big
    valid &= ~edge

    # Disparity with matching noise, quantised, back to depth.
    fb = camera.focal_px * camera.baseline_m
    disparity = fb / depth[valid]
    disparity = disparity + camera.disparity_sigma_px * rng.standard_normal(disparity.shape)
    disparity = np.round(disparity / camera.disparity_step_px) * camera.disparity_step_px
    measured = fb / disparity
    points = view.eye_m + directions[valid] * (measured / cos_axis[valid])[:, None]
    surface = view.eye_m + directions[valid] * distance[valid][:, None]
    return points, surface, triangle[valid]
