"""``teachpath demo``: the bundled synthetic scene, reconstructed, with its accuracy table."""

from __future__ import annotations

import argparse
from pathlib import Path

from service.cli.options import OneLineParser

#: The command's name, and its line in ``teachpath --help``.
NAME = "demo"
HELP = "run the bundled demo: a synthetic cylinder-edge trace and scan, reconstructed"


def add_parser(commands: argparse._SubParsersAction[OneLineParser]) -> None:
    demo = commands.add_parser(
        NAME,
        help=HELP,
        description="Generates the paper's Fig. 4 scene (a noisy trace along the circular edge "
        "of a cylinder and a misplaced, noisy scan of it), writes them as files, reconstructs "
        "them as `teachpath reconstruct` does and prints the accuracy table.",
    )
    demo.add_argument("--out-dir", default="demo_out", help="folder for all outputs")
    demo.add_argument("--seed", type=int, default=0, help="random seed of the scene")
    demo.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from drivers.calibration import write_calibration
    from drivers.scanning.pointcloud import write_scan
    from drivers.tracking.canonical_csv import write_trace_csv
    from recon import scenes
    from recon.evaluation import default_variants, evaluate, format_table
    from recon.reconstruct import reconstruct
    from recon.transforms import apply_transform, invert_transform
    from service.cli import main
    from service.demo import DEMO_T_BASE_TRACKER
    from service.plots import plot_reconstruction

    out_dir = Path(args.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    scene = scenes.cylinder_edge(args.seed)
    assert scene.scan is not None  # the cylinder scene is scanned
    trace_file, scan_file = out_dir / "trace.csv", out_dir / "scan.ply"
    write_trace_csv(trace_file, scene.recording)
    write_scan(scan_file, scene.scan)
    print(f"scene: {scene.description}")
    print(
        f"inputs: {trace_file} ({len(scene.recording)} samples), "
        f"{scan_file} ({len(scene.scan)} points)"
    )
    code = main(
        [
            "reconstruct",
            str(trace_file),
            "--scan",
            str(scan_file),
            "--out",
            str(out_dir / "reconstruction.csv"),
            "--plot",
            str(out_dir / "reconstruction.png"),
        ]
    )
    if code:
        return code
    table = format_table(evaluate(scene, default_variants()), title=scene.description)
    (out_dir / "accuracy.md").write_text(table + "\n")
    # The same reconstruction against the ground truth only the demo knows (the paper's Fig. 5).
    recon = reconstruct(scene.recording, scene.scan)
    plot_reconstruction(
        out_dir / "accuracy.png",
        recon,
        scan_m=apply_transform(invert_transform(scene.T_scan_tracker), scene.scan.points_m),
        truth_m=scene.truth_m,
        title="demo: error against the ground truth (tracker frame)",
    )
    print()
    print(table)
    # Where the demo stands the workpiece in front of the arm: the input of `teachpath plan`.
    placement = out_dir / "T_base_tracker.json"
    write_calibration(placement, "T_base_tracker", np.array(DEMO_T_BASE_TRACKER))
    print(
        f"\nwrote {out_dir / 'reconstruction.csv'}, {out_dir / 'reconstruction.png'}, "
        f"{out_dir / 'accuracy.md'}, {out_dir / 'accuracy.png'}, {placement}"
    )
    return 0
