"""Entry point of the ``msmill`` command.

Sub-command groups live in sibling modules (``ore``, ``psd``, ``breakage``,
``dem``, ``predict`` ...) and are registered in :data:`SUBCOMMANDS`. Every
command raises :class:`msmill.errors.MsmillInputError` for bad input; :func:`run`
prints that as one line on stderr and exits with status 2, never a traceback.
"""

from __future__ import annotations

import importlib
import os
import sys
import warnings
from pathlib import Path

import typer

from msmill._version import __version__
from msmill.errors import MsmillError, MsmillInputError, from_validation_error

#: width of --help written to a pipe or file (Rich's default there, 80 columns, cut option names short)
HELP_WIDTH_NOT_A_TERMINAL = 100


def _help_width() -> None:
    """Help written to a pipe or a file (no terminal, no ``COLUMNS``/``TERMINAL_WIDTH``) is 100 columns wide.

    Said through ``TERMINAL_WIDTH``, which Typer reads when it formats help or an error: importing its
    Rich formatting here (0.1-0.2 s) would slow every command run from a script or a pipe.
    """
    if os.environ.get("TERMINAL_WIDTH") or os.environ.get("COLUMNS") or sys.stdout.isatty():
        return
    if "typer.rich_utils" in sys.modules:  # already read the environment
        sys.modules["typer.rich_utils"].MAX_WIDTH = HELP_WIDTH_NOT_A_TERMINAL
    else:
        os.environ["TERMINAL_WIDTH"] = str(HELP_WIDTH_NOT_A_TERMINAL)

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
    ("circuit", "circuit", "circuit"),
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
    text = " ".join(str(message).split())
    if issubclass(category, RuntimeWarning) and "encountered in" in text:
        # a floating-point problem inside numpy: say where, not numpy's bare phrase
        where = Path(filename).stem
        return (f"warning: numerical problem in msmill ({text}, module {where}); "
                "results may be inaccurate: check the magnitudes of the inputs\n")
    return f"warning: {text}\n"


_SHOWN: set[str] = set()


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    text = _format_warning(message, category, filename, lineno)
    if text not in _SHOWN:  # each warning once per command, wherever it was raised from
        _SHOWN.add(text)
        (file or sys.stderr).write(text)


def _usage_error(exc: Exception) -> int:
    if type(exc).__name__ == "NoArgsIsHelpError":  # a bare group: its help, as click shows it
        exc.show()
        return getattr(exc, "exit_code", 2)
    ctx = getattr(exc, "ctx", None)
    where = f" (see '{ctx.command_path} --help')" if ctx is not None else ""
    msg = exc.format_message() if hasattr(exc, "format_message") else str(exc)
    param = getattr(exc, "param", None)
    if param is not None:
        opts = list(getattr(param, "opts", ()) or ()) or [str(getattr(param, "name", ""))]
        if not any(o in msg for o in opts):
            msg = f"{'/'.join(opts)}: {msg}"
    typer.echo(f"error: {' '.join(msg.split())}{where}", err=True)
    return getattr(exc, "exit_code", 2) or 2


def run(argv: list[str] | None = None) -> int:
    """Run the CLI and return its exit status (0 ok, 1 failure, 2 bad input).

    Every failure is one ``error:`` line on stderr, never a traceback; an
    unexpected exception (a bug) says so, exit status 1 (``MSMILL_DEBUG=1``
    shows the traceback). Warnings print once each as ``warning:`` lines.
    """
    warnings.formatwarning = _format_warning
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("default")  # each distinct warning once
            warnings.showwarning = _show_warning
            _SHOWN.clear()
            status = app(args=argv, prog_name="msmill", standalone_mode=False)
    except typer.Exit as exc:
        return exc.exit_code
    except typer.Abort:
        typer.echo("aborted", err=True)
        return 1
    except KeyboardInterrupt:
        typer.echo("aborted", err=True)
        return 130
    except typer.TyperException as exc:  # usage errors, bad parameters (click underneath)
        return _usage_error(exc)
    except MsmillInputError as exc:
        typer.echo(f"error: {exc}", err=True)
        return 2
    except MsmillError as exc:
        typer.echo(f"error: {exc}", err=True)
        return 1
    except FileNotFoundError as exc:
        typer.echo(f"error: file not found: {exc.filename}", err=True)
        return 2
    except OSError as exc:  # permissions, full disk, ...: the system's one-line reason
        typer.echo(f"error: {exc.filename or 'file'}: {exc.strerror or exc}", err=True)
        return 2 if isinstance(exc, PermissionError | IsADirectoryError | NotADirectoryError) else 1
    except MemoryError:
        typer.echo("error: out of memory (an input asks for more than this machine has)", err=True)
        return 1
    except Exception as exc:  # pydantic errors raised outside our loaders
        if type(exc).__name__ == "ValidationError" and hasattr(exc, "errors"):
            typer.echo(f"error: {from_validation_error(exc)}", err=True)
            return 2
        if os.environ.get("MSMILL_DEBUG"):
            raise
        msg = " ".join(str(exc).split())[:200]
        typer.echo(f"error: internal error, a bug in msmill ({type(exc).__name__}: {msg}); "
                   "please report it (MSMILL_DEBUG=1 shows the traceback)", err=True)
        return 1
    # click returns a command's typer.Exit(code) as the value in non-standalone mode
    return status if isinstance(status, int) else 0


def main() -> None:
    """Console-script entry point (the help width is set here, in msmill's own process only: a program
    that imports the CLI keeps its environment)."""
    _help_width()
    sys.exit(run())


_register()


if __name__ == "__main__":
    main()
