"""The trainers' recording hook: one greedy episode of the current networks per call.

:func:`record_training_episode` is what ``python -m plex_ma.train`` hands the trainers
(called every ``record_interval`` updates); see ``docs/viz.md``.
"""

from __future__ import annotations

import warnings
import weakref
from pathlib import Path

import torch

from plex_ma.trainers.evaluation import run_episodes
from plex_ma.trainers.logger import read_metrics

from .recorder import EpisodeRecorder

# Per trainer: the split its recordings use (the first one of val, train that exists).
_train_state: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def record_training_episode(trainer, path: str | Path | None = None, raise_errors: bool = False) -> Path | None:
    """Record one greedy episode of ``trainer``'s current networks into its run dir.

    Writes ``run_dir/recordings/update_<updates>.rrd`` (or ``path``): the first episode of
    the ``val`` split (``train`` if the scene source has no val split) on a separate
    one-world env, run by :func:`plex_ma.trainers.evaluation.run_episodes`, with the run's
    training curves so far (``train/...`` from ``metrics.jsonl``) in the same recording;
    RGB images are JPEG and images at most 128 px, to keep long runs' recordings small.
    Training is not disturbed: the actions are greedy (no sampling, so no RNG is drawn
    from) and the env is the recorder's own. A failure is reported as a warning and
    training goes on (``raise_errors=True`` raises instead). Returns the file, or None
    after a failure.
    """
    cfg = trainer.cfg
    updates = int(trainer.updates.get("executor", trainer.updates.get("policy", 0)))
    out = Path(path) if path is not None else Path(cfg.run_dir) / "recordings" / f"update_{updates:06d}.rrd"
    state = _train_state.setdefault(trainer, {})
    nets = trainer.nets
    modes = {k: m.training for k, m in nets.items()}
    threads = torch.get_num_threads()
    # Batch-1 inference gains nothing from more threads, and their spin-waiting beside
    # other busy processes made one episode up to ten times slower.
    torch.set_num_threads(1)
    try:
        rec = EpisodeRecorder(out, max_episodes=1, name=f"update {updates} (step {trainer.step:,})",
                              jpeg_quality=85, max_image_size=128)
        try:
            rec.log_training_history(read_metrics(cfg.run_dir))
        except OSError:
            pass
        for m in nets.values():
            m.eval()
        splits = [state["split"]] if "split" in state else ["val", "train"]
        for split in splits:
            try:
                run_episodes(cfg, nets, split=split, episodes=1, num_envs=1, recorder=rec)
            except (ValueError, FileNotFoundError, KeyError):
                if rec.began or split == splits[-1]:
                    raise
                continue  # no such split for this scene source: the env was never built
            state["split"] = split
            break
        return out
    except Exception as e:  # a recording must not end a long training run
        if raise_errors:
            raise
        warnings.warn(f"recording an episode at update {updates} failed: {type(e).__name__}: {e}", stacklevel=2)
        return None
    finally:
        for k, m in nets.items():
            m.train(modes[k])
        torch.set_num_threads(threads)


__all__ = ["record_training_episode"]
