"""The agents' actions, checked in one place for every env view.

Each view of the rules (``plex_nav_v0``'s AEC env and its ``Discrete`` compat view, the
PLEX and PointNav vector envs, the gymnasium envs) passes what a caller gave it through
these functions before anything in the worlds changes. A bad action raises
:class:`InvalidAction` (a ``ValueError``) that names the agent, the part of the action,
what was expected and what came, in the same words wherever it entered.

- :func:`discrete`: whole numbers in ``0..k-1`` (an executor's or a flat agent's navigation
  action, the planner's stop flag, a compat view's ``Discrete`` action);
- :func:`real`: finite real numbers of a given shape (a sub-goal, an ELI).
"""

from __future__ import annotations

import numpy as np


class InvalidAction(ValueError):
    """An action that does not fit the agent's action space; nothing was changed."""


def discrete(x, k: int, what: str, shape: tuple = (), names: tuple[str, ...] | None = None,
             integers_only: bool = False, per: str | None = None) -> np.ndarray:
    """``x`` as an int64 array of ``shape`` with every entry in ``0..k-1``.

    ``what`` names the action in messages (``"executor: action 'action'"``); ``names`` are
    the actions' names, ``per`` what each entry belongs to (``"world"``). Floats with whole
    values pass unless ``integers_only`` (gymnasium's ``Discrete`` takes integers only);
    bools, strings, dicts, NaN and fractions never do."""
    if isinstance(x, np.ndarray) and x.shape == tuple(shape) and x.dtype.kind in "iu" and x.size \
            and 0 <= np.minimum.reduce(x, None) and np.maximum.reduce(x, None) < k:
        return x.astype(np.int64, copy=False)  # the common case, before any message is built
    expect = f"{'integers' if shape else 'an integer'} in 0..{k - 1}"
    if names:
        expect += f" ({', '.join(names)})"
    if per:
        expect += f", one per {per}"

    def bad(problem: str) -> InvalidAction:
        return InvalidAction(f"{what} must be {expect}; {problem}")

    if isinstance(x, (dict, str, bytes)):
        raise bad(f"got a {type(x).__name__}")
    try:
        a = np.asarray(x)
    except (TypeError, ValueError, RuntimeError):
        raise bad(f"got {type(x).__name__}") from None
    if a.shape != tuple(shape):
        raise bad(f"got an array of shape {a.shape}" if shape or a.dtype == object
                  else f"got {type(x).__name__} of shape {a.shape} {x!r}")
    if a.dtype.kind == "b" or a.dtype.kind not in "iuf":
        raise bad(f"got dtype {a.dtype}" if shape or isinstance(x, np.ndarray) else f"got the {type(x).__name__} {x!r}")
    if a.dtype.kind == "f":
        if integers_only or not np.all(np.isfinite(a)) or np.any(a != np.round(a)):
            if shape:
                raise bad(f"got non-integer values {a.tolist()}")
            raise bad(f"got the float {x!r}" if integers_only and np.isfinite(a) and a == np.round(a)
                      else f"got the non-integer value {x!r}")
    a = a.astype(np.int64)
    out = np.flatnonzero((a < 0) | (a >= k))
    if len(out):
        raise bad(f"out of range: {per or 'entry'}(s) {out.tolist()} got {a.reshape(-1)[out].tolist()}" if shape
                  else f"{int(a)} is out of range")
    return a


def real(x, what: str, shape: tuple) -> np.ndarray:
    """``x`` as a float64 array of ``shape`` with every entry finite; ``what`` as in
    :func:`discrete`."""
    if isinstance(x, np.ndarray) and x.shape == tuple(shape) and x.dtype.kind == "f":
        a = np.asarray(x, dtype=np.float64)  # the common case: a float array of the right shape
        if np.isfinite(a).all():
            return a
    try:
        a = np.asarray(x)
        if np.iscomplexobj(a):
            raise TypeError
        a = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidAction(f"{what} must be real numbers, got {type(x).__name__}"
                            f"{' of dtype ' + str(x.dtype) if hasattr(x, 'dtype') else ''}") from None
    if a.shape != tuple(shape):
        raise InvalidAction(f"{what} has shape {a.shape}, expected {tuple(shape)}")
    if not np.isfinite(a).all():
        raise InvalidAction(f"{what} contains NaN or infinite values")
    return a
