"""``teachpath bundle export|import``: a session as one zip, to archive it or move it to
another data folder (see :mod:`service.bundles`)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from service.cli.options import OneLineParser, check_output

if TYPE_CHECKING:
    from service.settings import Settings
    from service.store import Store


#: The command's name, and its line in ``teachpath --help``.
NAME = "bundle"
HELP = "export a session as one zip, or import one"


def add_parser(commands: argparse._SubParsersAction[OneLineParser]) -> None:
    bundle = commands.add_parser(
        NAME,
        help=HELP,
        description="A bundle holds a session with its calibrations and every artifact (raw "
        "uploads, arrays, summaries) with their checksums. Settings such as "
        "TEACHPATH_DATABASE_URL apply as for `teachpath serve`.",
    )
    actions = bundle.add_subparsers(dest="action", required=True, parser_class=OneLineParser)
    export = actions.add_parser(
        "export",
        help="write a session's bundle",
        description="Writes SESSION_ID's bundle; exporting the same session again gives the "
        "same bytes.",
    )
    export.add_argument("session_id", metavar="SESSION_ID")
    _data_dir(export)
    export.add_argument("--out", required=True, metavar="SESSION.zip")
    export.set_defaults(handler=run_export)
    load = actions.add_parser(
        "import",
        help="import a session's bundle",
        description="Checks the whole bundle (checksums, manifest, schema) before it changes "
        "anything; importing a session that is already here with the same content does "
        "nothing.",
    )
    load.add_argument("bundle", metavar="SESSION.zip")
    _data_dir(load)
    load.set_defaults(handler=run_import)


def _data_dir(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data-dir", help="the service's data folder (default ./teachpath_data)")


def _settings(args: argparse.Namespace) -> Settings:
    from service.settings import Settings

    return Settings(**({"data_dir": args.data_dir} if args.data_dir else {}))


def _store(args: argparse.Namespace, *, must_exist: bool) -> Store:
    from service.store import Store

    settings = _settings(args)
    if (
        must_exist
        and not (settings.data_dir / "teachpath.db").is_file()
        and not (settings.database_url)
    ):
        raise ValueError(
            f"{settings.data_dir} holds no teachpath database: give the data folder of the "
            "service (--data-dir)"
        )
    return Store(settings.data_dir, settings.db_url)


def run_export(args: argparse.Namespace) -> int:
    from service.bundles import export_bundle

    out = check_output(args.out, ".zip")
    store = _store(args, must_exist=True)
    manifest = export_bundle(store, args.session_id, out)
    n_files = sum(1 + len(a.files) for a in manifest.artifacts)
    size_mb = out.stat().st_size / 1e6
    print(
        f"session {manifest.session.id} ({manifest.session.name!r}): {len(manifest.artifacts)} "
        f"artifacts, {n_files} files -> {out} ({size_mb:.1f} MB)"
    )
    return 0


def run_import(args: argparse.Namespace) -> int:
    from service.bundles import import_under

    source = Path(args.bundle)
    if not source.is_file():
        raise ValueError(f"{source} is not a file")
    store = _store(args, must_exist=False)
    with source.open("rb") as handle:
        # The limits and readers of the service's import: a bundle is no more trusted here.
        result = import_under(store, handle, _settings(args))
    if result.created:
        print(
            f"imported session {result.session_id}: {result.n_artifacts} artifacts, "
            f"{result.n_files} files ({result.n_bytes / 1e6:.1f} MB) into {store.data_dir}"
        )
    else:
        print(f"session {result.session_id} is already in {store.data_dir}: nothing changed")
    return 0
