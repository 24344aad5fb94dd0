"""Checkpoints: written atomically, loaded with ``weights_only=True``, never half-written.

A run dir holds ``latest.pt`` plus numbered ``ckpt_000123.pt`` files. A save writes a
temporary file in the same directory, fsyncs it and renames it into place, so a crash or
a full disk leaves the previous checkpoint untouched. A load that finds ``latest.pt``
corrupt or truncated says so and falls back to the newest numbered checkpoint that loads.

Only ``latest.pt`` holds the optimisers' state (Adam's two moments: twice the networks'
size); the numbered files leave it out (:data:`LATEST_ONLY`), so each costs a third of a
full checkpoint. A run resumed from ``latest.pt`` goes on exactly where it stopped; one
that falls back to a numbered file restarts its optimisers, and says so.

``pretrained:NAME`` names an agent shipped inside the package (``trainers/data/pretrained/
NAME.pt``; ``python -m plex_ma.pretrained`` lists them): a weights-only file whose weights
are stored as float16 (loaded back as float32) beside the config and the command that
trained it.
"""

from __future__ import annotations

import os
import re
import tempfile
import warnings
from pathlib import Path

import torch

_NUM = re.compile(r"ckpt_(\d+)\.pt$")


class CheckpointError(RuntimeError):
    """A checkpoint is missing, corrupt, truncated or incompatible; the message says which."""


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_FILE_MODE = 0o666 & ~_umask()  # what open() would give a new file: mkstemp's is 0o600


def atomic_save(obj, path: str | os.PathLike) -> None:
    """``torch.save`` to a temporary file beside ``path``, then renamed over it: a crash or
    a full disk leaves the previous file whole. The file gets open()'s usual permissions."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, _FILE_MODE)
        with os.fdopen(fd, "wb") as f:
            torch.save(obj, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


# What only latest.pt holds (see the module docstring).
LATEST_ONLY = ("optimizers",)


def save_checkpoint(run_dir: str | os.PathLike, state: dict, number: int, keep: int = 3) -> Path:
    """Write ``ckpt_<number>.pt`` (without :data:`LATEST_ONLY`) and ``latest.pt`` (all of
    ``state``) atomically; prune the numbered files but the newest ``keep``."""
    run_dir = Path(run_dir)
    numbered = run_dir / f"ckpt_{number:06d}.pt"
    atomic_save({k: v for k, v in state.items() if k not in LATEST_ONLY}, numbered)
    atomic_save(state, run_dir / "latest.pt")
    for old in sorted(_numbered(run_dir))[:-keep]:
        old[1].unlink(missing_ok=True)
    return numbered


def _numbered(run_dir: Path) -> list[tuple[int, Path]]:
    out = []
    for p in run_dir.glob("ckpt_*.pt"):
        m = _NUM.search(p.name)
        if m:
            out.append((int(m.group(1)), p))
    return out


PRETRAINED_PREFIX = "pretrained:"


def pretrained_dir() -> Path:
    return Path(__file__).resolve().parent / "data" / "pretrained"


def pretrained_names() -> list[str]:
    return sorted(p.stem for p in pretrained_dir().glob("*.pt"))


def resolve_checkpoint(path: str | os.PathLike) -> Path:
    """A checkpoint path, with ``pretrained:NAME`` mapped to the shipped file."""
    s = str(path)
    if s.startswith(PRETRAINED_PREFIX):
        name = s[len(PRETRAINED_PREFIX):]
        p = pretrained_dir() / f"{name}.pt"
        if not p.is_file():
            raise CheckpointError(f"no pretrained agent {name!r}; shipped: {pretrained_names()}")
        return p
    return Path(path)


def load_checkpoint(path: str | os.PathLike) -> dict:
    """Load one checkpoint file safely (``weights_only=True``) or raise CheckpointError.
    ``pretrained:NAME`` loads a shipped agent, its weights as float32."""
    path = resolve_checkpoint(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path}: {'is a directory' if path.is_dir() else 'does not exist'}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises several types for truncated / corrupt / unsafe files
        why = (str(e).strip().splitlines() or [""])[0].split(". ")[0]  # torch's first sentence: one line
        raise CheckpointError(f"checkpoint {path}: cannot be loaded (corrupt, truncated or not a "
                              f"plex-ma checkpoint): {type(e).__name__}{': ' + why if why else ''}") from None
    if not isinstance(state, dict) or "config" not in state or "format" not in state:
        raise CheckpointError(f"checkpoint {path}: not a plex-ma checkpoint (missing 'config'/'format')")
    if state.get("pretrained"):
        try:
            state["models"] = {k: {n: t.float() if t.is_floating_point() else t for n, t in sd.items()}
                               for k, sd in state["models"].items()}
        except (AttributeError, KeyError, TypeError) as e:
            raise CheckpointError(f"checkpoint {path}: malformed pretrained weights: {e}") from None
    return state


def export_pretrained(src: str | os.PathLike, dst: str | os.PathLike, command: str, notes: dict | None = None) -> Path:
    """Write the weights-only file of checkpoint ``src`` to ``dst`` (atomically): float16
    weights, the config, the step, ``command`` (how it was trained) and ``notes`` (e.g. its
    evaluation)."""
    state = load_checkpoint(src)
    out = {"format": state["format"], "pretrained": True, "config": state["config"], "step": state["step"],
           "updates": state.get("updates", {}), "command": str(command), "notes": dict(notes or {}),
           "models": {k: {n: t.half() if t.is_floating_point() else t for n, t in sd.items()}
                      for k, sd in state["models"].items()}}
    atomic_save(out, dst)
    return Path(dst)


def remove_stale_temporaries(run_dir: str | os.PathLike) -> list[Path]:
    """Delete the temporaries of saves cut short by a crash (``kill -9`` during a save); call it
    only when no save can be running (at start-up). Returns what it removed."""
    run_dir = Path(run_dir)
    gone = []
    if run_dir.is_dir():
        for p in run_dir.glob(".*.pt.*.tmp"):
            p.unlink(missing_ok=True)
            gone.append(p)
    return gone


def find_resumable(run_dir: str | os.PathLike) -> tuple[dict, Path] | None:
    """The newest good checkpoint of a run dir (``latest.pt`` first), or None if it has none.

    Corrupt files are reported with a warning and skipped."""
    run_dir = Path(run_dir)
    candidates = [run_dir / "latest.pt"] + [p for _, p in sorted(_numbered(run_dir), reverse=True)]
    seen_any = False
    for p in candidates:
        if not p.exists():
            continue
        seen_any = True
        try:
            return load_checkpoint(p), p
        except CheckpointError as e:
            warnings.warn(f"{e}; trying an older checkpoint", stacklevel=2)
    if seen_any:
        raise CheckpointError(f"run dir {run_dir}: every checkpoint in it is corrupt; move them away to start over")
    return None
