"""The ``render_mode="human"`` window of ``plex_nav_v0`` and ``plex_ma/PointNav-v0``.

A :class:`HumanViewer` shows each frame (the ``rgb_array`` top-down view) in a matplotlib
window, redrawn in place and paced to the env's ``render_fps``. It opens on the first
frame. Without a display (no ``DISPLAY`` / ``WAYLAND_DISPLAY`` on Linux, or matplotlib
resolving to a non-interactive backend such as Agg) or without matplotlib, it issues one
``UserWarning`` per process that says why, and every frame after that is dropped: the
env keeps working and ``render()`` returns ``None`` as PettingZoo and Gymnasium expect
of the human mode. Closing the window stops the display for that env; ``env.close()``
closes the window.
"""

from __future__ import annotations

import os
import sys
import time
import warnings

import numpy as np

# Backends that draw to files or memory only; matplotlib picks Agg when it finds no display.
_NON_INTERACTIVE = {"agg", "cairo", "pdf", "pgf", "ps", "svg", "template"}
_warned = False  # one warning per process, however many envs render headless


def display_problem() -> str | None:
    """Why no window can be shown here (a sentence), or None when one can."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return "no display (neither DISPLAY nor WAYLAND_DISPLAY is set)"
    try:
        import matplotlib
    except ImportError:
        return "matplotlib is not installed (pip install matplotlib)"
    backend = str(matplotlib.get_backend()).lower()
    if backend in _NON_INTERACTIVE or backend.startswith("module://matplotlib_inline"):
        return f"matplotlib's backend {backend!r} cannot open a window"
    return None


def _warn_once(name: str, why: str) -> None:
    global _warned
    if not _warned:
        _warned = True
        warnings.warn(f"{name}: render_mode='human' shows nothing here: {why}. The env runs on; "
                      "use render_mode='rgb_array' for the frames as arrays.", UserWarning, stacklevel=4)


class HumanViewer:
    """A live window for an env's frames (see the module docstring)."""

    def __init__(self, name: str, fps: float):
        self.name = name
        self.period = 1.0 / fps if fps and fps > 0 else 0.0
        self.shown = 0  # frames drawn in the window
        self._fig = None
        self._image = None
        self._last = 0.0
        self._off = False  # no display, or the window was closed

    def show(self, frame: np.ndarray) -> None:
        """Draw ``frame`` ((H, W, 3) uint8) in the window, opening it if needed."""
        if self._off:
            return
        if self._fig is None:
            why = display_problem()
            if why is not None:
                self._off = True
                _warn_once(self.name, why)
                return
            self._open(frame)
        import matplotlib.pyplot as plt

        if not plt.fignum_exists(self._fig.number):  # closed by the user
            self._off = True
            self._fig = self._image = None
            return
        if self._image.get_array().shape != frame.shape:  # another scene: another size
            self._image.remove()
            self._image = self._fig.axes[0].imshow(frame, interpolation="nearest")
        else:
            self._image.set_data(frame)
        self._fig.canvas.draw_idle()
        wait = self.period - (time.perf_counter() - self._last)
        self._fig.canvas.start_event_loop(max(wait, 1e-3))  # draws, handles window events, paces
        self._last = time.perf_counter()
        self.shown += 1

    def _open(self, frame: np.ndarray) -> None:
        import matplotlib.pyplot as plt

        self._fig = plt.figure(self.name)
        ax = self._fig.add_axes((0, 0, 1, 1))
        ax.set_axis_off()
        self._image = ax.imshow(frame, interpolation="nearest")
        plt.show(block=False)
        self._last = time.perf_counter()

    def close(self) -> None:
        if self._fig is not None:
            import matplotlib.pyplot as plt

            plt.close(self._fig)
        self._fig = self._image = None
