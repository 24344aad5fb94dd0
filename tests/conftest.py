"""Shared test settings."""

import os
import sys

import pytest

# The suite's torch waits passively, as plex_ma's commands do: its spinning threads would
# fight the simulator's on this 2-core machine (docs/performance.md). Read when torch loads.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402
from hypothesis import settings  # noqa: E402

# CI runs the property tests on fixed examples (``HYPOTHESIS_PROFILE=ci``, set by .ci/run),
# so that a run's verdict depends on the code alone; a local ``make test`` draws new
# examples every time and keeps exploring. A failure prints the seed to reproduce it.
settings.register_profile("ci", derandomize=True, database=None, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))


@pytest.fixture
def headless(monkeypatch):
    """No display, and the human render mode's once-per-process warning not yet given."""
    from plex_ma.envs import viewer

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    if not sys.platform.startswith("linux"):
        monkeypatch.setattr(viewer, "display_problem", lambda: "no display (test)")
    monkeypatch.setattr(viewer, "_warned", False)


@pytest.fixture(autouse=True, scope="module")
def one_torch_thread():
    # pytest runs two workers on the two cores; more torch threads per worker only fight
    # over them (and spinning OpenMP threads slow everything down many times over).
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
