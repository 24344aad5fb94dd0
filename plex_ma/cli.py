"""What the command lines share: a user error is one line on stderr with exit status 2,
and no traceback (``train``, ``evaluate``, ``record``, ``bench``, ``episodes``, ``scenes``,
``experiments``, ``pretrained``), and argparse types that name a bad value."""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path
from typing import NoReturn


class Parser(argparse.ArgumentParser):
    """argparse's parser whose errors are one line, ``PROG: error: MESSAGE`` (argparse
    prints its whole usage first; ``--help`` still shows it). Subcommands get this class
    too."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


def fail(message: object) -> NoReturn:
    """A user error found after parsing (a scene directory that does not exist, a corrupt
    checkpoint ...): ``error: MESSAGE`` on stderr, exit status 2."""
    print(f"error: {message}", file=sys.stderr)
    raise SystemExit(2)


def integer(least: int, most: int | None = None):
    """An argparse type: an integer in [least, most] (argparse names the flag in its error)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < least or (most is not None and value > most):
            bound = f"in [{least}, {most}]" if most is not None else f">= {least}"
            raise argparse.ArgumentTypeError(f"must be an integer {bound}, got {value}")
        return value

    return parse


def probability(text: str) -> float:
    """An argparse type: a number in [0, 1]."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be a probability in [0, 1], got {value}")
    return value


def unwritable(path: str, directory: bool = False) -> str | None:
    """Why a command could not write ``path`` (a file, or a directory it creates), or None:
    checked before any work, so a bad output path costs nothing and leaves nothing behind."""
    p = Path(path).expanduser()
    if p.exists() and p.is_dir() != directory:
        return f"{path!r} is {'not a directory' if directory else 'a directory'}"
    up = p if p.exists() and directory else p.parent
    while not up.exists():
        up = up.parent
    if not up.is_dir():
        return f"{path!r}: {str(up)!r} is not a directory"
    if not os.access(up, os.W_OK | os.X_OK) or (p.is_file() and not os.access(p, os.W_OK)):
        return f"{path!r}: not writable"
    try:  # a real probe too: os.access says yes to root everywhere, even in /proc
        tempfile.TemporaryFile(dir=up).close()
    except OSError as e:
        return f"{path!r}: cannot write in {str(up)!r} ({e.strerror})"
    return None


def output_path(directory: bool = False):
    """An argparse type: a path the command will write (see :func:`unwritable`)."""

    def parse(text: str) -> str:
        why = unwritable(text, directory)
        if why:
            raise argparse.ArgumentTypeError(why)
        return text

    return parse
