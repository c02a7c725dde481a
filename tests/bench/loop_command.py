"""The speed benchmark's baseline: a whole ``reconstruct`` command whose per-point stage is a
straightforward per-point loop of the paper's Eq. (4) (:func:`tests.reference_loop.reconstruct_loop`
with ``method="paper"``), reading and writing the same files as ``teachpath reconstruct``.

Usage: ``python -m tests.bench.loop_command TRACE.csv SCAN.ply OUT.csv``
"""

from __future__ import annotations

import sys

import numpy as np

from drivers.scanning.pointcloud import read_scan
from drivers.tracking.readers import read_trace
from recon.recon_params import ReconParams
from tests.reference_loop import reconstruct_loop


def main(argv: list[str]) -> int:
    trace, scan, out = argv
    points = reconstruct_loop(
        read_trace(trace).recording, read_scan(scan).scan, ReconParams(method="paper")
    )
    np.savetxt(out, points, delimiter=",", header="x,y,z", comments="", fmt="%.9g")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
