"""``teachpath replay``: archived sessions run again and compared with what they stored (see
:mod:`service.replay`), on a local Dask cluster or an existing one."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from service.cli.options import EXIT_FAILURE, OneLineParser, check_output, positive

if TYPE_CHECKING:
    from distributed import Client

    from service.replay import Row


#: The command's name, and its line in ``teachpath --help``.
NAME = "replay"
HELP = "re-run archived sessions (bundles) and report what changed"


def add_parser(commands: argparse._SubParsersAction[OneLineParser]) -> None:
    replay = commands.add_parser(
        NAME,
        help=HELP,
        description="Runs every stored reconstruction of each bundle again (and plans every "
        "stored trajectory again from its reconstruction), with the stored parameters or "
        "--params, one Dask task per bundle, and writes a CSV report (and a PNG summary "
        "beside it). Exits 1 when a result moved more than the tolerance or failed.",
    )
    replay.add_argument(
        "sources", nargs="+", metavar="BUNDLE_OR_FOLDER", help="SESSION.zip files or folders"
    )
    replay.add_argument(
        "--params",
        metavar="PARAMS.json",
        help='parameters to use instead of the stored ones: {"reconstruction": {...}, '
        '"plan": {...}}',
    )
    where = replay.add_mutually_exclusive_group()
    where.add_argument(
        "--workers", type=int, help="workers of the local cluster (default: one per core)"
    )
    where.add_argument(
        "--scheduler",
        metavar="tcp://HOST:PORT",
        help="an existing Dask cluster (its workers must be able to read the bundles)",
    )
    replay.add_argument(
        "--tolerance-m",
        type=positive,
        default=1e-4,
        help="a result that moved more than this has changed (default %(default)s m)",
    )
    replay.add_argument("--report", required=True, metavar="REPORT.csv")
    replay.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from service.replay import Overrides, find_bundles, plot_report, run_replay

    report = check_output(args.report, ".csv")
    if args.workers is not None and args.workers < 1:
        raise ValueError("--workers must be at least 1")
    if args.scheduler is not None and not args.scheduler.startswith(("tcp://", "tls://")):
        raise ValueError(
            f"--scheduler must be an address like tcp://HOST:PORT, not {args.scheduler}"
        )
    overrides = Overrides.none()
    if args.params:
        path = Path(args.params)
        if not path.is_file():
            raise ValueError(f"{args.params} is not a file")
        if path.stat().st_size > 1 << 20:
            raise ValueError(f"{args.params} is larger than 1 MB: not a parameter file")
        overrides = Overrides.from_json(path.read_text(errors="replace"), name=args.params)
    bundles = find_bundles(args.sources)
    interactive = sys.stderr.isatty()

    def show_cluster(client: Client) -> None:
        where = args.scheduler or f"a local cluster of {len(client.scheduler_info()['workers'])}"
        link = client.dashboard_link if args.scheduler else None
        print(
            f"replaying {len(bundles)} bundles on {where}"
            + (f" (dashboard {link})" if link else ""),
            file=sys.stderr,
            flush=True,
        )

    def progress(done: int, total: int, rows: list[Row]) -> None:
        width = 30
        filled = width * done // total
        failed = [r for r in rows if r["status"] == "failed"]
        line = f"[{'#' * filled}{'.' * (width - filled)}] {done}/{total} {rows[0]['bundle']}"
        if failed:
            print(
                f"\n{rows[0]['bundle']}: {failed[0]['error']}"
                if interactive
                else f"{rows[0]['bundle']}: failed: {failed[0]['error']}",
                file=sys.stderr,
            )
        if interactive:
            print(
                f"\r{line[:120]:<120}",
                end="" if done < total else "\n",
                file=sys.stderr,
                flush=True,
            )
        elif done == total or done % max(1, total // 10) == 0:
            print(f"{done}/{total} bundles replayed", file=sys.stderr, flush=True)

    summary = run_replay(
        bundles,
        report_path=report,
        overrides=overrides,
        tolerance_m=args.tolerance_m,
        workers=args.workers,
        scheduler=args.scheduler,
        on_result=progress,
        on_cluster=show_cluster,
    )
    png = report.with_suffix(".png")
    plot_report(report, png, args.tolerance_m)
    print(
        f"{summary.n_bundles} bundles, {summary.n_rows} results in {summary.wall_s:.1f} s: "
        f"{summary.n_moved} moved more than {args.tolerance_m:g} m, {summary.n_failed} failed; "
        f"report {report}, summary {png}"
    )
    return 0 if summary.passed else EXIT_FAILURE
