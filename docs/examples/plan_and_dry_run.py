"""Plan the whole motion of a UR5e along a reconstructed path, then dry-run it.

Run from the repository root: ``.venv/bin/python docs/examples/plan_and_dry_run.py``. The same
pipeline functions run behind ``teachpath plan`` and ``teachpath dry-run`` and the service's
jobs (``service.pipelines``): planning checks the joint limits, singularities and the TCP speed,
and the whole motion against the cell (here: the mounting plane and the scanned workpiece); the
dry run executes every sample on the simulated arm, faster than real time.
"""

import numpy as np

from recon.plan_params import PlanParams
from recon.recon_params import ReconParams
from recon.reconstruct import reconstruct
from recon.scenes import cylinder_edge
from service import pipelines

scene = cylinder_edge(seed=0)
result = reconstruct(scene.recording, scene.scan, params=ReconParams(radius_m=0.004))

# Where the tracker's frame is in the robot's base frame (from a calibration: `teachpath
# calibrate`); here the workpiece sits 0.45 m in front of the base and 5 cm up.
T_base_tracker = np.array([[1, 0, 0, 0.45], [0, 1, 0, 0.1], [0, 0, 1, 0.05], [0, 0, 0, 1.0]])
# The scan's structure near the path, where the reconstruction placed it: the tool axis follows
# the surface's normals.
placed = pipelines.place_scan(scene.scan, result)
plan = pipelines.plan(
    result,
    params=PlanParams(robot="ur5e", speed_m_s=0.05),
    T_base_tracker=T_base_tracker,
    scan_model=placed.model,
    scan=scene.scan,  # the workpiece is part of the cell the motion is checked against
)
print("\n".join(plan.lines()[:6]))

dry = pipelines.dry_run(plan.trajectory)
print("\n".join(dry.lines()[:3]))
print("passed" if dry.passed else "FAILED")
