"""The layers import downward only: import-linter's contracts in pyproject.toml hold, and a
violating import is caught."""

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
pytestmark = pytest.mark.skipif(importlib.util.find_spec("importlinter") is None,
                                reason="import-linter is not installed (pip install -e '.[test]')")

sys.path.insert(0, str(ROOT / "scripts"))
import lint_imports  # noqa: E402


def test_contracts_kept(tmp_path):
    out = lint_imports.lint(lint_imports.stage(tmp_path), capture=True)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "3 kept, 0 broken" in out.stdout


@pytest.mark.parametrize("module, bad_import, contract", [
    ("envs/sim/core.py", "import plex_ma.envs.rules", "the simulator knows nothing of agents"),
    ("envs/rules.py", "import plex_ma.networks", "plex-ma layers"),
    ("trainers/ppo.py", "import plex_ma.viz.recorder", "plex-ma layers"),
])
def test_an_upward_import_is_caught(tmp_path, module, bad_import, contract):
    staged = lint_imports.stage(tmp_path)
    target = staged / "plex_ma" / module
    target.write_text(target.read_text() + f"\n{bad_import}  # an upward import\n")
    out = lint_imports.lint(staged, capture=True)
    assert out.returncode != 0
    assert f"{contract} BROKEN" in out.stdout, out.stdout
