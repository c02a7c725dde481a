"""Reconstruct a traced path with the scan of the workpiece, and measure it against the truth.

Run from the repository root: ``.venv/bin/python docs/examples/reconstruct_a_trace.py``.
The scene is synthetic (a cylinder's top edge, traced by a simulated shaky hand, scanned by a
simulated depth camera), so the true edge is known. With your own files, read them instead::

    from drivers.scanning.base import read_scan
    from drivers.tracking.readers import read_trace
    trace = read_trace("trace.csv").recording   # metres, tracker frame
    scan = read_scan("scan.ply")                # metres, scan frame
"""

from scipy.spatial import cKDTree

from recon.recon_params import ReconParams
from recon.reconstruct import reconstruct
from recon.scenes import cylinder_edge

scene = cylinder_edge(seed=0)
result = reconstruct(scene.recording, scene.scan, params=ReconParams(radius_m=0.004))

# Distance of each reconstructed point from the true edge (densely sampled), tracker frame.
error_m, _ = cKDTree(scene.truth_m).query(result.points_m)
trace_error_m, _ = cKDTree(scene.truth_m).query(scene.recording.points_m)
print(f"{len(result.points_m)} points, registered to the scan (T_scan_tracker found by ICP)")
for name, error in (("trace", trace_error_m), ("reconstruction", error_m)):
    print(f"{name:>14}: mean {error.mean() * 1000:.2f} mm, max {error.max() * 1000:.2f} mm")
