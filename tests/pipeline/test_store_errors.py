"""A store that cannot be opened is one line naming the URL and the cause (issue 40); reads never create one."""

from __future__ import annotations

import pytest

from msmill.cli.main import run as cli


def _corrupt(path):
    path.write_bytes(b"not a database" * 100)
    return str(path)


@pytest.mark.parametrize("make,expect", [
    (lambda d: str(d / "typo" / "store.sqlite"), "no such file"),          # a mistyped path
    (lambda d: _corrupt(d / "c.sqlite"), "not a database"),
    (lambda d: str(d), "this is a folder"),
    (lambda d: "foo://bar", "a SQLAlchemy URL"),
    (lambda d: "postgresql://me:secret@127.0.0.1:1/none", "can be opened"),  # nothing listens on port 1
])
def test_unopenable_stores_are_one_line_errors(tmp_path, capsys, make, expect):
    url = make(tmp_path)
    for cmd in (["db", "info"], ["db", "list"], ["db", "show", "1"], ["campaign", "status", "c"]):
        assert cli([*cmd, "--db", url]) == 2, cmd
        err = capsys.readouterr().err
        assert err.startswith("error: --db:") and expect in err and err.count("\n") == 1, err
        assert "secret" not in err  # passwords are not printed
    assert not (tmp_path / "typo").exists()  # a read never creates folders or a store


def test_an_inverted_range_is_an_error(tmp_path, capsys):
    db = str(tmp_path / "s.sqlite")
    assert cli(["db", "upgrade", "--db", db]) == 0
    capsys.readouterr()
    assert cli(["db", "list", "--db", db, "--size-mm", "40:20"]) == 2
    assert "LOW <= HIGH" in capsys.readouterr().err
    assert cli(["db", "list", "--db", db, "--size-mm", "20:40"]) == 0


@pytest.mark.parametrize("args,field", [
    (["", ], "campaign name"), (["../../etc/x"], "campaign name"), (["a/b"], "campaign name"),
    ([".hidden"], "campaign name"), (["ok", "--ore", "Gold"], "--ore"),
    (["ok", "--set", "max_time_s=-5"], "--max-time-s"), (["ok", "--set", "measure_s=0"], "--measure-s"),
])
def test_campaign_create_checks_its_arguments_at_once(tmp_path, capsys, args, field):
    db = str(tmp_path / "s.sqlite")
    assert cli(["campaign", "create", *args, "--db", db]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {field}:") and err.count("\n") == 1, err
    assert cli(["campaign", "status", "ok", "--db", db]) == 2  # nothing was created
