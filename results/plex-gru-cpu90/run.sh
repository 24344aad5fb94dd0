#!/bin/bash
# 90-minute cpu-preset PLEX-GRU training, then evaluation on the 1,000 test episodes (procgen) and r2v test.
cd /work/main && source .venv/bin/activate
date > /work/runs/cpu90/start.txt
git rev-parse HEAD >> /work/runs/cpu90/start.txt
timeout -s INT 5400 python -m plex_ma.train --preset cpu --total-steps 10000000 --run-dir /work/runs/cpu90/run --no-progress > /work/runs/cpu90/train.log 2>&1
date > /work/runs/cpu90/train_end.txt
python -m plex_ma.evaluate --checkpoint /work/runs/cpu90/run/latest.pt --split test --episodes 1000 --num-envs 16 --json /work/runs/cpu90/eval_test_procgen.json > /work/runs/cpu90/eval_test_procgen.log 2>&1
date > /work/runs/cpu90/eval_end.txt
