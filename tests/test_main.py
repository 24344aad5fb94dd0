"""``python -m plex_ma``: lists every command of the package, one line each, and runs them."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from plex_ma import __main__ as cli

PACKAGE = Path(cli.__file__).resolve().parent


def test_no_command_lists_every_command_one_line_each():
    out = subprocess.run([sys.executable, "-m", "plex_ma"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0].startswith("usage: python -m plex_ma COMMAND")
    listed = [m.group(1) for line in lines if (m := re.match(r"  (\S+)\s{2,}\S", line))]
    assert listed == list(cli.COMMANDS)
    for name, text in cli.COMMANDS.items():
        assert sum(line.split()[:1] == [name] for line in lines) == 1 and text in out.stdout


def test_the_list_is_the_package_command_lines():
    # every module of the package with a command line is listed, and only those
    have_main = {p.stem for p in PACKAGE.glob("*.py")
                 if p.name != "__main__.py" and 'if __name__ == "__main__":' in p.read_text()}
    have_main |= {p.parent.name for p in PACKAGE.glob("*/__main__.py")}
    assert have_main == set(cli.COMMANDS)


def test_a_command_runs_its_module(capsys, monkeypatch):
    # as from a shell, the command's module is not imported yet (else runpy warns)
    monkeypatch.delitem(sys.modules, "plex_ma.episodes", raising=False)
    argv = list(sys.argv)
    with pytest.raises(SystemExit) as e:
        cli.main(["episodes", "--help"])
    assert e.value.code == 0 and sys.argv == argv
    out = capsys.readouterr().out
    assert out.startswith("usage: python -m plex_ma.episodes") and "{make,show}" in out


def test_unknown_command_names_it_and_lists_the_commands(capsys):
    assert cli.main(["trian"]) == 2
    err = capsys.readouterr().err
    assert "unknown command 'trian'" in err and "  train " in err
    assert cli.main(["--help"]) == 0 and "  evaluate " in capsys.readouterr().out
