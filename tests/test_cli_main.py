from msmill import __version__
from msmill.cli.main import run


def test_version(capsys):
    assert run(["--version"]) == 0
    assert __version__ in capsys.readouterr().out


def test_unknown_command_is_usage_error(capsys):
    assert run(["no-such-command"]) == 2
