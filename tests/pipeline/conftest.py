"""Store backends for the tests: a SQLite file and a real PostgreSQL server.

PostgreSQL: ``MSMILL_TEST_PG_URL`` (``.ci/run`` starts a server and sets it),
else a throwaway server started here if Debian's binaries are installed
(``scripts/pg_throwaway.py``), else the PostgreSQL cases skip -- unless
``MSMILL_REQUIRE_PG=1`` (CI), which turns a missing server into a failure.
Every test gets a fresh database. The surrogate fitted on the shipped table's
runs (``fitted``, ``saved``) is the root conftest's.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import tempfile
import uuid
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[2]


def _pg_helper():
    spec = importlib.util.spec_from_file_location("pg_throwaway", ROOT / "scripts" / "pg_throwaway.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="session")
def pg_server_url():
    """URL of a PostgreSQL server's maintenance database (or skip / fail, see the module docstring)."""
    url = os.environ.get("MSMILL_TEST_PG_URL")
    if url:
        yield url
        return
    helper = _pg_helper()
    folder = None
    try:
        if helper.pg_bin() is None:
            raise RuntimeError("PostgreSQL binaries not found")
        folder = tempfile.mkdtemp(prefix="msmill-pg-")
        url = helper.start(folder)
    except Exception as exc:
        if os.environ.get("MSMILL_REQUIRE_PG") == "1":
            pytest.fail(f"PostgreSQL required (MSMILL_REQUIRE_PG=1) but unavailable: {exc}")
        pytest.skip(f"no PostgreSQL server: {exc}")
    yield url
    helper.stop(folder)
    shutil.rmtree(folder, ignore_errors=True)


def _fresh_pg_database(server_url: str):
    from sqlalchemy import create_engine, text

    name = f"t_{uuid.uuid4().hex[:12]}"
    admin = create_engine(server_url, isolation_level="AUTOCOMMIT")
    with admin.connect() as c:
        c.execute(text(f'CREATE DATABASE "{name}"'))
    base = server_url.rsplit("/", 1)[0]
    return admin, name, f"{base}/{name}"


@pytest.fixture(params=["sqlite", "postgresql"])
def store_url(request, tmp_path):
    """URL of an empty store database on each backend."""
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'store.sqlite'}"
        return
    admin, name, url = _fresh_pg_database(request.getfixturevalue("pg_server_url"))
    yield url
    from sqlalchemy import text

    with admin.connect() as c:
        c.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
    admin.dispose()


@pytest.fixture
def store(store_url):
    from msmill.pipeline.store import Store

    st = Store(store_url)
    yield st
    st.close()
