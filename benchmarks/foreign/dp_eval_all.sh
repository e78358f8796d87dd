#!/bin/bash
# The issue-18 figures for the Diffusion-Policy-format checkpoint (DP's own code trained it; seeds 100000-100099).
set -e
cd "$(dirname "$0")/../.."
P=runs/dp/train_lowdim/checkpoints/latest.ckpt
WM=runs/pusht-cpu/wm-phase2/checkpoints/last.ckpt
R=results/foreign/dp
S=100000:100100
J=${WORKERS:-1}
G=.venv/bin/gpc
# BC as Diffusion Policy samples (DDPM, 100 steps), to set beside DP's own evaluation
[ -f $R/bc-ddpm100/summary.json ] || $G eval $P --seeds $S --out $R/bc-ddpm100 --workers $J
# The planners draw K proposals per decision: DDIM 10 steps (the same trained network); BC paired with them likewise
D="--method ddim --steps 10"
[ -f $R/bc/summary.json ] || $G eval $P --seeds $S --out $R/bc --workers $J $D
[ -f $R/rank-opt-10x30/summary.json ] || $G eval $P --planner rank-opt -K 10 -M 30 --world-model $WM --seeds $S --out $R/rank-opt-10x30 --workers $J $D
[ -f $R/rank-K100/summary.json ] || $G eval $P --planner rank -K 100 --world-model $WM --seeds $S --out $R/rank-K100 --workers $J $D
[ -f $R/gt-sim-K100/summary.json ] || $G eval $P --planner gt-sim -K 100 --seeds $S --out $R/gt-sim-K100 --workers $J $D
$G compare $R/rank-K100 $R/rank-opt-10x30 --baseline $R/bc --ceiling $R/gt-sim-K100 --out $R/table.md \
  --title "A Diffusion-Policy-format checkpoint (DP's own code, human data) as GPC's proposal source, paired over seeds 100000-100099"
