"""Slices across a reconstructed path on a real part: what the scan, the part, the trace and the
reconstruction look like in the plane across the path, where the reconstruction is worst.

For looking, not for asserting: ``python -m tests.realparts_slices PART#CURVE[:KIND] [SEED]``
writes ``slices-PART-CURVE.png`` (tracker frame, millimetres).
"""

from __future__ import annotations

import sys

import numpy as np
from scipy.spatial import cKDTree

from recon.metrics import distance_to_curve
from recon.transforms import apply_transform, invert_transform

MM = 1e-3


def slice_indices(recon_points_m, truth_m, count: int = 5) -> list[int]:
    """The worst points of a reconstruction, at least 10 mm apart, and its two ends."""
    error = distance_to_curve(recon_points_m, truth_m)
    chosen: list[int] = [0, len(error) - 1]
    for index in np.argsort(error)[::-1]:
        if len(chosen) >= count + 2:
            break
        if all(np.linalg.norm(recon_points_m[index] - recon_points_m[c]) > 10 * MM for c in chosen):
            chosen.append(int(index))
    return chosen


def _section(points, width_m, frame):
    """The points within ``width_m`` of the slice's plane (and its half-width of its centre),
    in the slice's axes, millimetres (K, 2)."""
    centre, tangent, a, b, half_width_m = frame
    rel = points - centre
    near = (np.abs(rel @ tangent) < width_m) & (np.linalg.norm(rel, axis=1) < half_width_m)
    return np.column_stack([rel[near] @ a, rel[near] @ b]) / MM


def plot_slices(scene, recons: dict, part, path, *, indices=None, half_width_m=12 * MM):
    """One panel per slice: scan points near the plane (grey), the part's section (black), the
    true curve (green), the trace (blue) and each reconstruction (one colour each).

    Parameters
    ----------
    scene : Scene
    recons : dict of str to Reconstruction
        Labelled reconstructions of the scene (the first one picks the slices).
    part : Part
        For the section of the true surface.
    path : str or Path
        Where the PNG goes.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    first = next(iter(recons.values()))
    if indices is None:
        indices = slice_indices(first.points_m, scene.truth_m)
    scan = apply_transform(invert_transform(scene.T_scan_tracker), scene.scan.points_m)
    truth_tree = cKDTree(scene.truth_m)
    rng = np.random.default_rng(0)
    v, f = part.vertices_m, part.triangles
    # The part's surface, densely sampled, for its section.
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    n = 600_000
    tri = rng.choice(len(f), size=n, p=area / area.sum())
    r1, r2 = rng.uniform(size=(2, n))
    flip = r1 + r2 > 1
    r1, r2 = np.where(flip, 1 - r1, r1), np.where(flip, 1 - r2, r2)
    surface = v[f[tri, 0]] + r1[:, None] * (v[f[tri, 1]] - v[f[tri, 0]])
    surface += r2[:, None] * (v[f[tri, 2]] - v[f[tri, 0]])
    columns = min(len(indices), 4)
    rows = int(np.ceil(len(indices) / columns))
    fig, axes = plt.subplots(rows, columns, figsize=(4.2 * columns, 4.2 * rows), squeeze=False)
    colours = ["tab:red", "tab:orange", "tab:purple", "tab:brown"]
    for ax, index in zip(axes.ravel(), indices, strict=False):
        _, g = truth_tree.query(first.points_m[index])
        centre = scene.truth_m[g]
        tangent = scene.truth_m[min(g + 5, len(scene.truth_m) - 1)] - scene.truth_m[max(g - 5, 0)]
        tangent /= np.linalg.norm(tangent)
        helper = [0.0, 0.0, 1.0] if abs(tangent[2]) < 0.9 else [1.0, 0.0, 0.0]
        a = np.cross(tangent, helper)
        a /= np.linalg.norm(a)
        b = np.cross(tangent, a)

        frame = (centre, tangent, a, b, half_width_m)
        s = _section(scan, 0.75 * MM, frame)
        ax.scatter(s[:, 0], s[:, 1], s=2, c="0.6", label="scan")
        m = _section(surface, 0.1 * MM, frame)
        ax.scatter(m[:, 0], m[:, 1], s=0.5, c="k", label="part")
        ax.scatter([0], [0], marker="*", s=120, c="tab:green", label="true curve", zorder=5)
        trace = _section(first.input_points_m, 0.6 * MM, frame)
        ax.scatter(
            trace[:, 0], trace[:, 1], marker="o", s=40, c="tab:blue", label="trace", zorder=5
        )
        for colour, (label, recon) in zip(colours, recons.items(), strict=False):
            r = _section(recon.points_m, 0.6 * MM, frame)
            ax.scatter(r[:, 0], r[:, 1], marker="x", s=60, c=colour, label=label, zorder=6)
        error = distance_to_curve(first.points_m[index : index + 1], scene.truth_m)[0]
        ax.set_title(f"point {index}: {error / MM:.2f} mm off", fontsize=9)
        ax.set_aspect("equal")
        ax.set_xlim(-half_width_m / MM, half_width_m / MM)
        ax.set_ylim(-half_width_m / MM, half_width_m / MM)
        ax.grid(True, lw=0.3)
    for ax in axes.ravel()[len(indices) :]:
        ax.axis("off")
    axes[0, 0].legend(fontsize=7, loc="lower left")
    fig.suptitle(f"{scene.name}: slices across the path (mm, tracker frame)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv: list[str]) -> None:
    from tests.corpus import load_part
    from tests.realparts import VARIANTS, benchmark_cases, scene_of

    name, _, kind = argv[0].partition(":")
    part_name, _, index = name.partition("#")
    seed = int(argv[1]) if len(argv) > 1 else 0
    (case,) = [c for c in benchmark_cases((part_name,)) if c.index == int(index)]
    scene = scene_of(case, seed, kind or "edge")
    recons = {label: VARIANTS[label].run(scene, seed) for label in ("known", "trace")}
    out = f"slices-{part_name}-{index}-{kind or 'edge'}-{seed}.png"
    plot_slices(scene, recons, load_part(part_name), out)
    print(out)


if __name__ == "__main__":
    main(sys.argv[1:])
