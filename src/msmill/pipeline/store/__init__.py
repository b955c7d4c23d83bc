"""SQL training store of DEM runs (SQLAlchemy 2.0 ORM, Alembic migrations).

See ``docs/campaign.md`` for the schema. Entry point: :class:`Store`
(``from msmill.pipeline.store import Store``).
"""

from __future__ import annotations

from typing import Any

__all__ = ["RunRecord", "Store", "default_url"]


def __getattr__(name: str) -> Any:  # lazy: importing the package does not import SQLAlchemy
    if name in __all__:
        from msmill.pipeline.store import core

        return getattr(core, name)
    raise AttributeError(name)
