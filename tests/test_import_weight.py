"""Commands load only what they use (issue 39): `import msmill`, `msmill --help` and `msmill ore list` start light."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

HEAVY = ("matplotlib", "sqlalchemy", "dask", "distributed", "fastapi", "numba", "sklearn", "scipy.stats",
         "msmill.dem", "pandas")

PROBE = """
import contextlib, io, json, sys
code = sys.argv[1]
if code == "import":
    import msmill
else:
    from msmill.cli.main import run
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        try:
            run(code.split())
        except SystemExit:
            pass
print(json.dumps(sorted(m for m in json.loads(sys.argv[2]) if m in sys.modules)))
"""


@pytest.mark.parametrize("command,allowed", [("import", ()), ("--help", ()), ("ore list", ()),
                                             ("ore show UG2", ())])
def test_light_commands_do_not_load_heavy_libraries(command, allowed):
    out = subprocess.run([sys.executable, "-c", PROBE, command, json.dumps(HEAVY)], capture_output=True,
                         text=True, timeout=120, check=True)
    loaded = set(json.loads(out.stdout.strip().splitlines()[-1])) - set(allowed)
    assert not loaded, f"'{command}' imports {sorted(loaded)}"


def test_a_command_in_a_pipe_does_not_load_the_help_formatting():
    """Written to a pipe (a script, `| head`), a command does not import Typer's Rich help formatting (0.1-0.2 s)
    just to set the help width it would use; help itself still gets the 100 columns (tests/test_cli_help.py)."""
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "TERMINAL_WIDTH", "LINES")}
    out = subprocess.run([sys.executable, "-c", PROBE, "ore list", json.dumps(["typer.rich_utils", "markdown_it"])],
                         capture_output=True, text=True, timeout=120, check=True, env=env)
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []
