#!/bin/bash
# PLEX-GRU on procgen+r2v, cpu preset, 25 minutes beside the PLEX run, then 200 test episodes
cd /work/main && source .venv/bin/activate
date > /work/runs/mix25/start.txt
timeout -s INT 1500 python -m plex_ma.train --preset cpu --scenes procgen+r2v --total-steps 10000000 --run-dir /work/runs/mix25/run --no-progress > /work/runs/mix25/train.log 2>&1
date > /work/runs/mix25/train_end.txt
python -m plex_ma.evaluate --checkpoint /work/runs/mix25/run/latest.pt --split test --scenes r2v --episodes 200 --num-envs 16 --json /work/runs/mix25/eval_test_r2v.json > /work/runs/mix25/eval_test_r2v.log 2>&1
date > /work/runs/mix25/eval_end.txt
