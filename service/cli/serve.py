"""``teachpath serve``: the HTTP service (REST API and the teach-pendant page)."""

from __future__ import annotations

import argparse

from service.cli.options import OneLineParser

#: The command's name, and its line in ``teachpath --help``.
NAME = "serve"
HELP = "start the HTTP service (REST API, teach-pendant page)"


def add_parser(commands: argparse._SubParsersAction[OneLineParser]) -> None:
    serve = commands.add_parser(
        NAME,
        help=HELP,
        description="Starts the service. Settings also come from TEACHPATH_* environment "
        "variables (TEACHPATH_TOKEN, TEACHPATH_UR_HOST, TEACHPATH_DATABASE_URL, ...).",
    )
    serve.add_argument("--host", help="address to listen on (default 127.0.0.1)")
    serve.add_argument("--port", type=int, help="port (default 8000; 0 picks a free one)")
    serve.add_argument(
        "--data-dir", help="folder for the database and arrays (default ./teachpath_data)"
    )
    serve.add_argument(
        "--demo",
        action="store_true",
        help="create the demo session (a synthetic cylinder trace and scan)",
    )
    serve.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    import socket

    import uvicorn

    from service.app import create_app
    from service.pairing import CODE_TTL_S
    from service.settings import Settings

    overrides = {
        k: v
        for k, v in {"host": args.host, "port": args.port, "data_dir": args.data_dir}.items()
        if v is not None
    }
    if args.demo:
        overrides["demo"] = True
    settings = Settings(**overrides)
    token = settings.access_token()
    app = create_app(settings)
    # Bind first, so the printed URL has the real port (also with --port 0).
    sock = socket.socket(socket.AF_INET6 if ":" in settings.host else socket.AF_INET)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    # Accepted connections inherit it: without it, Nagle's algorithm meets the client's delayed
    # ACK and small responses wait 40 ms (measured: p50 50 ms for a 4 ms request).
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    sock.bind((settings.host, settings.port))
    host, port = sock.getsockname()[:2]
    shown = f"[{host}]" if ":" in host else host
    print(f"teachpath is serving {settings.data_dir}")
    print(f"open http://{shown}:{port}/?token={token}")
    print(f"API: http://{shown}:{port}/docs (send 'Authorization: Bearer {token}')")
    print(f"guide: http://{shown}:{port}/guide/ (built by make docs)")
    print(
        f"pairing code for another screen: {app.state.pairing.issue()} (once, within "
        f"{CODE_TTL_S / 60:.0f} min; "
        "a signed-in pendant makes new ones: Pair a screen)",
        flush=True,
    )
    config = uvicorn.Config(app, log_level="warning")
    uvicorn.Server(config).run(sockets=[sock])
    return 0
