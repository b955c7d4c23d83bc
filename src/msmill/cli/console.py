"""The one terminal console of the CLI: user text is never read as Rich markup.

An ore name, a run-file title or a note may contain ``[``...``]`` (``title =
"[/bold] closing tag"``, ``stage speeds [1500.0, 3000.0] rpm``); with markup on,
Rich raises ``MarkupError`` or silently drops the brackets. Every command prints
through :func:`console`, which has markup, emoji codes and highlighting off, so
text is shown exactly as written.
"""

from __future__ import annotations

from rich.console import Console


def console(width: int = 120, stderr: bool = False) -> Console:
    """A Rich console that prints text verbatim (no markup, no ``:emoji:``, no highlighting).

    Parameters
    ----------
    width : int
        Line width (characters); fixed so tables do not depend on the terminal.
    stderr : bool
        Print to standard error instead of standard output.
    """
    return Console(width=width, soft_wrap=False, markup=False, emoji=False, highlight=False,
                   stderr=stderr)
