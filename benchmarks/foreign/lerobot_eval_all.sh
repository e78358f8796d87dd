#!/bin/bash
REPO=$(cd "$(dirname "$0")/../.." && pwd)
# The issue-18 figures for the LeRobot-trained keypoint policy (seeds 100000-100099).
set -e
cd "$(dirname "$0")/../.."
P=runs/lerobot/train_keypoints/checkpoints/last
WM=runs/pusht-cpu/wm-phase2/checkpoints/last.ckpt
R=results/foreign/lerobot
S=100000:100100
J=${WORKERS:-1}
G=.venv/bin/gpc
[ -f $R/bc/summary.json ] || $G eval $P --seeds $S --out $R/bc --workers $J
[ -f $R/rank-opt-10x30/summary.json ] || $G eval $P --planner rank-opt -K 10 -M 30 --world-model $WM --seeds $S --out $R/rank-opt-10x30 --workers $J
[ -f $R/rank-K100/summary.json ] || $G eval $P --planner rank -K 100 --world-model $WM --seeds $S --out $R/rank-K100 --workers $J
[ -f $R/gt-sim-K100/summary.json ] || $G eval $P --planner gt-sim -K 100 --seeds $S --out $R/gt-sim-K100 --workers $J
$G compare $R/rank-K100 $R/rank-opt-10x30 --baseline $R/bc --ceiling $R/gt-sim-K100 --out $R/table.md \
  --title "A LeRobot-trained keypoint policy (LeRobot 0.4.4, human data) as GPC's proposal source, paired over seeds 100000-100099"
# LeRobot's own evaluation in gym-pusht (its own initial-state draws for these seeds)
if [ ! -f $R/lerobot_eval/eval_info.json ]; then
  (cd /tmp && HF_HUB_OFFLINE=1 OMP_NUM_THREADS=1 /work/refenv/bin/python -m lerobot.scripts.lerobot_eval \
    --policy.path=$REPO/$P/pretrained_model --env.type=pusht --env.obs_type=environment_state_agent_pos \
    --eval.n_episodes=100 --eval.batch_size=50 --seed=100000 --policy.device=cpu --output_dir=$REPO/$R/lerobot_eval)
fi
