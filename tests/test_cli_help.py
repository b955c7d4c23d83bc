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
