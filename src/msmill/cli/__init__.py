"""Command-line interface (Typer). Holds no physics: it calls the public API."""
