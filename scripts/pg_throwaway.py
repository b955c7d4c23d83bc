"""Start or stop a throwaway PostgreSQL server for the store tests (Debian's ``postgresql`` binaries).

Usage::

    python scripts/pg_throwaway.py start DIR   # prints the SQLAlchemy URL on stdout
    python scripts/pg_throwaway.py stop DIR

The cluster lives in ``DIR`` (trust authentication, listening on 127.0.0.1
at a free port, fsync off: for tests only). Run as root, the server runs as
the ``postgres`` user (PostgreSQL refuses to run as root). ``.ci/run`` uses
this and exports the URL as ``MSMILL_TEST_PG_URL``; ``tests/pipeline``
starts one itself when that variable is not set and the binaries exist.
"""

from __future__ import annotations

import glob
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path


def pg_bin() -> Path | None:
    """Folder of ``initdb``/``pg_ctl`` (newest Debian version, else PATH), None if not installed."""
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"), key=lambda p: int(Path(p).parts[4]))
    if found:
        return Path(found[-1]).parent
    exe = shutil.which("initdb")
    return Path(exe).parent if exe else None


def _as_owner(cmd: list[str]) -> list[str]:
    if os.geteuid() == 0:
        return ["runuser", "-u", "postgres", "--", *cmd]
    return cmd


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start(folder: str | Path) -> str:
    """Create and start a cluster in ``folder``; returns its SQLAlchemy URL."""
    bin_ = pg_bin()
    if bin_ is None:
        raise RuntimeError("PostgreSQL is not installed (Debian: apt-get install -y postgresql)")
    d = Path(folder).resolve()
    data = d / "data"
    d.mkdir(parents=True, exist_ok=True)
    if os.geteuid() == 0:
        shutil.chown(d, "postgres")
    run = {"check": True, "stdout": subprocess.DEVNULL, "stderr": subprocess.PIPE}
    subprocess.run(_as_owner([str(bin_ / "initdb"), "-D", str(data), "-A", "trust", "-U", "postgres",
                              "-E", "UTF8"]), **run)
    port = _free_port()
    opts = f"-p {port} -k {d} -c listen_addresses=127.0.0.1 -c fsync=off -c max_connections=50"
    subprocess.run(_as_owner([str(bin_ / "pg_ctl"), "-D", str(data), "-o", opts, "-l", str(d / "server.log"),
                              "-w", "start"]), **run)
    url = f"postgresql+psycopg://postgres@127.0.0.1:{port}/postgres"
    (d / "url").write_text(url + "\n", encoding="utf-8")
    return url


def stop(folder: str | Path) -> None:
    """Stop the cluster in ``folder`` (fast shutdown)."""
    bin_ = pg_bin()
    data = Path(folder).resolve() / "data"
    if bin_ is not None and data.exists():
        subprocess.run(_as_owner([str(bin_ / "pg_ctl"), "-D", str(data), "-m", "fast", "-w", "stop"]),
                       check=False, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


if __name__ == "__main__":
    if len(sys.argv) != 3 or sys.argv[1] not in ("start", "stop"):
        sys.exit("usage: pg_throwaway.py start|stop DIR")
    if sys.argv[1] == "start":
        print(start(sys.argv[2]))
    else:
        stop(sys.argv[2])
