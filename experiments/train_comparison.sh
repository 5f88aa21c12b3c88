#!/bin/bash
# Trains the comparison systems (NSRR, NSRR-fast, KPN, MLP) on the default data at 4x
# and 2x, with the step budgets that fit a 2-core CPU (about 1.5 hours in all; see
# docs/comparison.md for the measured time). The checkpoints land in runs/<model>-x<f>/
# and their parameters are exported to experiments/weights/<model>-x<f>.msgpack (with
# the config and the per-epoch log), which the README's evaluation command reads:
#   python -m jtus.evaluate --models jau tus shipped 'nsrr=experiments/weights/nsrr-x{f}.msgpack' ...
# Pass --perceptual-weights FILE through EXTRA to add NSRR's VGG-16 term.
set -euo pipefail
cd "$(dirname "$0")/.."
common="--seq-len 6 --loss-frames 2 --crop 64 --batch 4 --no-eval --quiet ${EXTRA:-}"
for f in ${FACTORS:-4 2}; do
  python -m jtus.train --model mlp --loss l1 --factor $f --epochs 8 --steps-per-epoch 100 $common --workdir runs/mlp-x$f
  python -m jtus.train --model kpn --loss kpn --factor $f --epochs 4 --steps-per-epoch 50 $common --workdir runs/kpn-x$f
  python -m jtus.train --model nsrr-fast --loss ssim --factor $f --epochs 3 --steps-per-epoch 40 $common --workdir runs/nsrr-fast-x$f
  python -m jtus.train --model nsrr --loss ssim --factor $f --epochs 3 --steps-per-epoch 30 $common --workdir runs/nsrr-x$f
  for m in mlp kpn nsrr-fast nsrr; do
    python -c "from jtus import train; train.export_params('runs/$m-x$f', 'experiments/weights/$m-x$f')"
  done
done
