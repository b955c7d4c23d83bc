"""``msmill serve``: the local what-if web app and HTTP API (see ``docs/web.md``)."""

from __future__ import annotations

import socket
from typing import Annotated

import typer

from msmill.errors import MsmillInputError


def serve(
    host: Annotated[str, typer.Option("--host", help="Interface to bind (127.0.0.1: this machine only).")] = "127.0.0.1",
    port: Annotated[int, typer.Option("--port", help="TCP port (0 picks a free one).")] = 8765,
    log_level: Annotated[str, typer.Option("--log-level", help="uvicorn log level.")] = "warning",
) -> None:
    """Start the web app: open http://HOST:PORT/ in a browser; the API is described at /docs."""
    if not 0 <= port <= 65535:
        raise MsmillInputError("--port", port, "an integer port 0-65535")
    levels = ("critical", "error", "warning", "info", "debug")
    if log_level not in levels:
        raise MsmillInputError("--log-level", log_level, f"one of {', '.join(levels)}")
    import uvicorn

    from msmill.web.app import create_app
    from msmill.web.service import PredictionService

    if port == 0:
        with socket.socket() as s:
            s.bind((host, 0))
            port = s.getsockname()[1]
    svc = PredictionService()
    typer.echo("msmill serve: warming the model with the shipped UG2 example ...")
    warm_s = svc.warm()  # the first request then costs what later ones do
    typer.echo(f"msmill serve: ready in {warm_s:.1f} s at http://{host}:{port}/  (API: http://{host}:{port}/docs; "
               "Ctrl-C stops)")
    try:
        uvicorn.run(create_app(svc), host=host, port=port, log_level=log_level)
    except OSError as exc:
        raise MsmillInputError("--port", port, f"a free port on {host} ({exc.strerror})") from None
