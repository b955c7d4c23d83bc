"""``--help`` written to a pipe or a file (CI logs, ``| less``) keeps every option name whole (issue 40 item 7)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

#: the commands whose option tables Rich cut short at its 80-column default (``--passing-size-…``)
COMMANDS = ["predict", "sweep", "optimize", "calibrate"]


@pytest.mark.parametrize("command", COMMANDS)
def test_help_to_a_pipe_keeps_option_names_whole(command):
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "TERMINAL_WIDTH", "LINES")}
    out = subprocess.run([sys.executable, "-m", "msmill", command, "--help"], capture_output=True, text=True,
                         timeout=120, env=env, check=True).stdout
    assert "…" not in out
    assert max(len(line) for line in out.splitlines()) <= 100
    if command == "sweep":
        assert "--passing-size-mm" in out and "--no-capacity-check" in out


def test_a_stated_width_is_kept():
    env = {**os.environ, "COLUMNS": "80"}
    out = subprocess.run([sys.executable, "-m", "msmill", "sweep", "--help"], capture_output=True, text=True,
                         timeout=120, env=env, check=True).stdout
    assert max(len(line) for line in out.splitlines()) <= 80


def _commands(cmd, path=()):
    yield path, cmd
    if hasattr(cmd, "commands"):  # a group (typer carries its own click)
        for name, sub in cmd.commands.items():
            yield from _commands(sub, (*path, name))


def test_no_help_text_loses_a_bracketed_word_to_rich_markup():
    """Rich reads ``[gpu]`` in a help string as a style tag and drops it (``pip install 'msmill[gpu]'`` showed
    as ``'msmill'``): every bracketed word of every option's help must be escaped (``\\\\[gpu]``)."""
    import re

    import typer

    from msmill.cli.main import _register, app

    _register()
    bad, seen = [], []
    for path, cmd in _commands(typer.main.get_command(app)):
        for p in cmd.params:
            seen.append(p)
            for m in re.finditer(r"(?<!\\)\[([A-Za-z_][\w.-]*)\]", getattr(p, "help", None) or ""):
                bad.append(f"{' '.join(path)} {'/'.join(getattr(p, 'opts', [p.name]))}: [{m.group(1)}]")
    assert not bad, bad
    assert len(seen) > 100  # the walk reached the sub-commands' options
