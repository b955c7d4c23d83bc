"""Entry point of the ``msmill`` command.

Sub-command groups live in sibling modules (``ore``, ``psd``, ``breakage``,
``dem``, ``predict`` ...) and are registered in :data:`SUBCOMMANDS`. Every
command raises :class:`msmill.errors.MsmillInputError` for bad input; :func:`run`
prints that as one line on stderr and exits with status 2, never a traceback.
"""

from __future__ import annotations

import importlib
import sys
import warnings

import typer

from msmill._version import __version__
from msmill.errors import MsmillError, MsmillInputError, from_validation_error

app = typer.Typer(
    name="msmill",
    help="Predict what a multi-shaft vertical impact mill does to rock.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

# (module under msmill.cli, attribute holding a typer.Typer or a command function, name)
SUBCOMMANDS: list[tuple[str, str, str]] = [
    ("dem", "app", "dem"),
    ("ore", "app", "ore"),
    ("psd", "app", "psd"),
    ("breakage", "app", "breakage"),
    ("predict", "predict", "predict"),
    ("db", "app", "db"),
    ("campaign", "app", "campaign"),
    ("serve", "serve", "serve"),
    ("surrogate", "app", "surrogate"),
    ("validate", "validate", "validate"),
    ("validate", "calibrate", "calibrate"),
    ("sweep", "sweep", "sweep"),
    ("sweep", "optimize", "optimize"),
    ("report", "report", "report"),
]


def _version_callback(value: bool) -> None:
    if value:
        typer.echo(f"msmill {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(
        False, "--version", callback=_version_callback, is_eager=True, help="Show the version and exit."
    ),
) -> None:
    """msmill: multi-shaft mill comminution model."""


def _register() -> None:
    for module_name, attr, name in SUBCOMMANDS:
        module = importlib.import_module(f"msmill.cli.{module_name}")
        obj = getattr(module, attr)
        if isinstance(obj, typer.Typer):
            app.add_typer(obj, name=name)
        else:
            app.command(name=name)(obj)


def _format_warning(message, category, filename, lineno, line=None) -> str:
    return f"warning: {message}\n"


def run(argv: list[str] | None = None) -> int:
    """Run the CLI and return its exit status (0 ok, 1 failure, 2 bad input)."""
    warnings.formatwarning = _format_warning
    try:
        app(args=argv, prog_name="msmill", standalone_mode=False)
    except typer.Exit as exc:
        return exc.exit_code
    except typer.TyperException as exc:  # usage errors, bad parameters (click underneath)
        exc.show()
        return getattr(exc, "exit_code", 2)
    except typer.Abort:
        typer.echo("aborted", err=True)
        return 1
    except MsmillInputError as exc:
        typer.echo(f"error: {exc}", err=True)
        return 2
    except MsmillError as exc:
        typer.echo(f"error: {exc}", err=True)
        return 1
    except FileNotFoundError as exc:
        typer.echo(f"error: file not found: {exc.filename}", err=True)
        return 2
    except Exception as exc:  # pydantic errors raised outside our loaders
        if type(exc).__name__ == "ValidationError" and hasattr(exc, "errors"):
            typer.echo(f"error: {from_validation_error(exc)}", err=True)
            return 2
        raise
    return 0


def main() -> None:
    """Console-script entry point."""
    sys.exit(run())


_register()


if __name__ == "__main__":
    main()
