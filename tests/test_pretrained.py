"""The agents shipped in the package: pretrained:NAME loads, acts, fine-tunes, and bad
names or files fail clearly."""

from __future__ import annotations


import pytest
import torch

from plex_ma.config import preset_defaults, replace, validate
from plex_ma.trainers.evaluation import load_policies, run_episodes
from plex_ma.trainers.base import saved_config
from plex_ma.trainers.checkpoint import CheckpointError, export_pretrained, load_checkpoint, pretrained_names
from plex_ma.trainers import make_trainer


def test_shipped_agents_are_small_and_say_how_they_were_trained():
    assert {"plex-gru", "ppo-gru"} <= set(pretrained_names())
    for name in ("plex-gru", "ppo-gru"):
        st = load_checkpoint(f"pretrained:{name}")
        assert st["pretrained"] and "python -m plex_ma.train" in st["command"]
        assert st["config"]["method"] == name and st["step"] > 0
        for sd in st["models"].values():  # loaded back as float32
            assert all(t.dtype == torch.float32 for t in sd.values() if t.is_floating_point())


def test_pretrained_plex_gru_runs_an_episode():
    cfg, nets = load_policies("pretrained:plex-gru")
    [res] = run_episodes(cfg, nets, split="val", episodes=1, num_envs=1)
    assert res["steps"] >= 1 and 0.0 <= res["success"] <= 1.0


def test_unknown_pretrained_name_and_fine_tuning(tmp_path):
    with pytest.raises(CheckpointError, match="no pretrained agent 'nope'"):
        load_checkpoint("pretrained:nope")
    cfg = replace(preset_defaults("cpu", "ppo-gru"), run_dir=str(tmp_path / "ft"), total_steps=64,
                  num_envs=2, rollout_steps=16, progress=False, record_interval=0,
                  checkpoint="pretrained:ppo-gru")
    with pytest.raises(CheckpointError, match="executor_no_reversal"):  # trained with the turn mask
        make_trainer(validate(replace(cfg, executor_no_reversal=False)))
    t = make_trainer(validate(cfg))
    shipped = load_checkpoint("pretrained:ppo-gru")["models"]["policy"]
    for k, v in t.nets["policy"].state_dict().items():
        torch.testing.assert_close(v, shipped[k])  # starts from the shipped weights
    assert t.step == 0
    t.close()
    bad = replace(cfg, run_dir=str(tmp_path / "bad"), executor_hidden=64)
    with pytest.raises(CheckpointError, match="executor_hidden"):
        make_trainer(validate(bad))


def test_export_round_trip(tmp_path):
    src = tmp_path / "src.pt"
    st = load_checkpoint("pretrained:ppo-gru")
    torch.save({**st, "pretrained": False}, src)
    out = export_pretrained(src, tmp_path / "x.pt", "cmd", {"note": 1})
    back = load_checkpoint(out)
    assert back["command"] == "cmd" and back["notes"] == {"note": 1}
    for k, v in st["models"]["policy"].items():
        torch.testing.assert_close(back["models"]["policy"][k], v, atol=1e-2, rtol=1e-2)


def test_planner_architecture_must_match_to_fine_tune(tmp_path):
    """The shipped PLEX-GRU's planner has the value-iteration module: a run without it
    refuses the weights, naming the setting. It was trained with the cpu preset's 48 px, and
    a run at 64 px refuses it too, naming the resolution."""
    assert load_checkpoint("pretrained:plex-gru")["config"]["planner_value_iteration"] is True
    cfg = replace(preset_defaults("cpu"), run_dir=str(tmp_path / "ft"), total_steps=64, num_envs=2,
                  rollout_steps=16, progress=False, record_interval=0, checkpoint="pretrained:plex-gru",
                  planner_value_iteration=False,
                  executor_no_reversal=saved_config(load_checkpoint("pretrained:plex-gru")).executor_no_reversal)
    with pytest.raises(CheckpointError, match="planner_value_iteration"):
        make_trainer(validate(cfg))
    with pytest.raises(CheckpointError, match="resolution=48 but this run asks for 64"):
        make_trainer(validate(replace(cfg, resolution=64, planner_value_iteration=True)))


@pytest.mark.parametrize("name", ["plex-gru", "ppo-gru"])
def test_printed_command_trains_the_shipped_config(name, capsys):
    """``python -m plex_ma.pretrained`` prints, for each shipped agent, the train command whose
    config equals the stored one in every field that shapes training."""
    import dataclasses
    import shlex

    from plex_ma.config import OUTPUT_FIELDS, command, parse
    from plex_ma.pretrained import main

    stored = saved_config(load_checkpoint(f"pretrained:{name}"))
    cmd = command(stored)
    assert main([]) == 0 and cmd in capsys.readouterr().out
    back = parse(shlex.split(cmd)[3:])
    a, b = dataclasses.asdict(stored), dataclasses.asdict(back)
    assert {k: v for k, v in a.items() if k not in OUTPUT_FIELDS} == {k: v for k, v in b.items() if k not in OUTPUT_FIELDS}
