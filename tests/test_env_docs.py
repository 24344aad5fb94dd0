"""The env's reference page (``help(plex_nav_v0)``) against the code: its "## Arguments"
table names every argument with its true default, its NAME line is a plain summary, and
``env()`` adds the wrappers its docstring names."""

import ast
import dataclasses
import inspect
import pydoc
import re

import pytest

from plex_ma.envs import plex_nav_v0
from plex_ma.envs.plex_nav import _OrderEnforcing
from plex_ma.envs.rules import PlexConfig


def _section(doc: str, heading: str) -> str:
    """The text under ``## heading`` up to the next ``## `` heading."""
    parts = re.split(r"^## ", doc, flags=re.M)
    found = [p for p in parts if p.startswith(heading + "\n")]
    assert len(found) == 1, f"the docstring has no single '## {heading}' section"
    return found[0][len(heading) + 1:]


def argument_rows() -> list[tuple[str, object]]:
    """(name, stated default) for every argument in the table; a row that lists several
    names lists as many defaults, in the same order."""
    rows = []
    for line in _section(plex_nav_v0.__doc__, "Arguments").splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if not line.startswith("|") or len(cells) < 3 or cells[0] in ("argument", "") or set(cells[0]) <= set("-"):
            continue
        names = re.findall(r"`([A-Za-z_]\w*)`", cells[0])
        defaults = ast.literal_eval(f"[{cells[1]}]")
        assert names and len(names) == len(defaults), f"row {line!r}: {len(names)} names, {len(defaults)} defaults"
        rows.extend(zip(names, defaults))
    return rows


def _arguments() -> dict[str, object]:
    """Every env argument with its default: the init fields of PlexConfig and render_mode."""
    out = {}
    for f in dataclasses.fields(PlexConfig):
        if f.init:
            out[f.name] = f.default_factory() if f.default is dataclasses.MISSING else f.default
    out["render_mode"] = inspect.signature(plex_nav_v0.raw_env.__init__).parameters["render_mode"].default
    return out


def test_table_parser_splits_rows_of_several_names():
    rows = dict(argument_rows())
    assert rows["slack_reward"] == -0.01 and rows["subgoal_reward"] == 1
    assert rows["pose_noise"] == (0.0, 0.0)


def test_arguments_table_lists_every_env_argument():
    names = [n for n, _ in argument_rows()]
    assert len(names) == len(set(names)), f"listed twice: {sorted({n for n in names if names.count(n) > 1})}"
    args = _arguments()
    assert sorted(set(args) - set(names)) == [], "env arguments missing from plex_nav_v0's '## Arguments' table"
    assert sorted(set(names) - set(args)) == [], "'## Arguments' rows that are not env arguments"


@pytest.mark.parametrize("name, stated", argument_rows(), ids=[n for n, _ in argument_rows()])
def test_arguments_table_states_the_true_default(name, stated):
    true = _arguments()[name]
    assert stated == true and isinstance(stated, bool) == isinstance(true, bool), \
        f"{name}: the table says {stated!r}, the default is {true!r}"


def test_help_name_line_is_a_plain_summary():
    synopsis, _ = pydoc.splitdoc(plex_nav_v0.__doc__)
    assert synopsis and "\n" not in synopsis and not synopsis.startswith(("#", "`", "|"))
    assert "plex_nav_v0" in synopsis


def test_env_adds_the_wrappers_its_docstring_names():
    e = plex_nav_v0.env(num_scenes=1, resolution=32)
    try:
        assert type(e) is _OrderEnforcing and type(e.env) is plex_nav_v0.raw_env
    finally:
        e.close()
    assert "order-enforcing" in plex_nav_v0.env.__doc__
