#!/bin/bash
# Resume the 90-minute cpu-preset PLEX-GRU run (session 2) for 30 more minutes: 2 hours of training in all.
# Then evaluate on the 1,000 procgen test episodes and 200 r2v test episodes.
cd /work/main && source .venv/bin/activate
date > /work/runs/cpu120/start.txt
git rev-parse HEAD >> /work/runs/cpu120/start.txt
timeout -s INT 1800 python -m plex_ma.train --preset cpu --total-steps 10000000 --run-dir /work/runs/cpu120/run --no-progress > /work/runs/cpu120/train.log 2>&1
date > /work/runs/cpu120/train_end.txt
python -m plex_ma.evaluate --checkpoint /work/runs/cpu120/run/latest.pt --split test --episodes 1000 --num-envs 16 --json /work/runs/cpu120/eval_test_procgen.json > /work/runs/cpu120/eval_test_procgen.log 2>&1
python -m plex_ma.evaluate --checkpoint /work/runs/cpu120/run/latest.pt --split test --scenes r2v --episodes 200 --num-envs 16 --json /work/runs/cpu120/eval_test_r2v.json > /work/runs/cpu120/eval_test_r2v.log 2>&1
date > /work/runs/cpu120/eval_end.txt
