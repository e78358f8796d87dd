#!/bin/bash
REPO=$(cd "$(dirname "$0")/../.." && pwd)
# LeRobot's own training (lerobot 0.4.4 in the throwaway env) of a CPU-sized keypoint diffusion policy on the
# human Push-T demonstrations exported by `gpc data export ../shared/data/pusht_human_train.zarr --no-images`.
cd /tmp
export HF_HUB_OFFLINE=1 OMP_NUM_THREADS=${THREADS:-1}
exec /work/refenv/bin/python -m lerobot.scripts.lerobot_train \
  --dataset.repo_id=local/pusht_human_keypoints --dataset.root=$REPO/runs/lerobot/pusht_human_keypoints \
  --policy.type=diffusion --policy.device=cpu --policy.push_to_hub=false \
  --policy.down_dims='[64,128,256]' --policy.diffusion_step_embed_dim=128 \
  --policy.noise_scheduler_type=DDIM --policy.num_inference_steps=10 \
  --policy.normalization_mapping='{"VISUAL": "MEAN_STD", "STATE": "MIN_MAX", "ENV": "MIN_MAX", "ACTION": "MIN_MAX"}' \
  --policy.optimizer_lr=1e-3 \
  --output_dir=$REPO/runs/lerobot/train_keypoints --steps=${STEPS:-8000} --batch_size=64 \
  --log_freq=200 --save_freq=2000 --eval_freq=0 --num_workers=0 --seed=0 --wandb.enable=false
