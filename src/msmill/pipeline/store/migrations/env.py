"""Alembic environment of the training store.

The store runs migrations programmatically (:meth:`msmill.pipeline.store.Store.upgrade`),
passing an open connection in ``config.attributes["connection"]``; the URL in
the config is used otherwise (``alembic -x`` is not needed).
"""

from __future__ import annotations

from alembic import context
from sqlalchemy import create_engine

from msmill.pipeline.store.schema import Base

config = context.config
target_metadata = Base.metadata


def _run(connection) -> None:
    context.configure(connection=connection, target_metadata=target_metadata,
                      render_as_batch=connection.dialect.name == "sqlite")
    with context.begin_transaction():
        context.run_migrations()


def run_migrations_online() -> None:
    """Run against ``config.attributes["connection"]`` or a new engine on the configured URL."""
    connection = config.attributes.get("connection")
    if connection is not None:
        _run(connection)
        return
    engine = create_engine(config.get_main_option("sqlalchemy.url"))
    with engine.connect() as conn:
        _run(conn)
    engine.dispose()


if context.is_offline_mode():
    context.configure(url=config.get_main_option("sqlalchemy.url"), target_metadata=target_metadata,
                      literal_binds=True)
    with context.begin_transaction():
        context.run_migrations()
else:
    run_migrations_online()
