# Two entry points (see README): `make train` and `make test`. Both create or reuse a
# local virtual environment in .venv and install torch==2.13.0 from pip's configured sources
# before the package (the CPU build where they provide it; README's Install names its index).
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python

.PHONY: setup train test bench clean

$(VENV)/.installed: pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e ".[test]"
	touch $@

setup: $(VENV)/.installed

# The main job: PLEX-GRU with the cpu preset, its whole 2,048,000-step budget (the recipe and
# seed of pretrained:plex-gru; about an hour on 2 cores), then a greedy evaluation on 100
# fixed validation episodes. A shorter TRAIN_STEPS decays the learning rates over that.
TRAIN_STEPS ?= 2048000
TRAIN_SEED ?= 2
RUN_DIR ?= runs/quickstart
train: $(VENV)/.installed
	$(PY) -m plex_ma.train --preset cpu --method plex-gru --seed $(TRAIN_SEED) --total-steps $(TRAIN_STEPS) --run-dir $(RUN_DIR)
	$(PY) -m plex_ma.evaluate --checkpoint $(RUN_DIR)/latest.pt --split val --episodes 100 --json $(RUN_DIR)/eval_val.json

test: $(VENV)/.installed
	$(PY) -m pytest -q -n 2 tests

bench: $(VENV)/.installed
	$(PY) -m plex_ma.bench sim --num-envs 64 --resolution 128

clean:
	rm -rf $(VENV) runs *.egg-info
