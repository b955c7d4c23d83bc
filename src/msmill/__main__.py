"""``python -m msmill``: the same as the ``msmill`` command."""

from msmill.cli.main import main

if __name__ == "__main__":
    main()
