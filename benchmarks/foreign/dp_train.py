"""Train a real Diffusion Policy (real-stanford/diffusion_policy @5ba07ac) low-dim Push-T policy on CPU with DP's own code.

Run from OUTSIDE the repository (its datasets/ folder shadows HF datasets):
  cd /tmp && OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 nice -n 5 /work/refenv/bin/python benchmarks/foreign/dp_train.py \
      --steps N [--bench SECONDS] [--resume]

What DP's own TrainDiffusionUnetLowdimWorkspace.run() does, minus wandb/env-rollouts/topk, on CPU:
hydra-composed cfg -> workspace (seeds 42, builds model, ema_model, AdamW) -> PushTLowdimDataset from cfg.task.dataset
-> dataset.get_normalizer() -> set_normalizer on model and ema_model -> DataLoader -> DP's get_scheduler('cosine')
-> DP's EMAModel(cfg.ema) -> loop: compute_loss, backward, optimizer.step, zero_grad, lr_scheduler.step, ema.step.
Nothing here is DP code; DP is imported from /tmp/dp_src.
"""
import argparse
import json
import os
import sys
import time
import types
import typing
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

# never import from the repository (its top-level datasets/ shadows Hugging Face datasets)
sys.path[:] = [p for p in sys.path if not str(Path(p or os.getcwd()).resolve()).startswith(str(REPO))]

import numpy as np  # noqa: E402
import torch  # noqa: E402

DP_SRC = Path(os.environ.get("DP_SRC", "/tmp/dp_src"))
OUT = Path(REPO / "runs/dp/train_lowdim")
ZARR = "/work/shared/data/pusht_human_train.zarr"


def setup_dp():
    """Same shims as tests/fixtures/foreign/make_fixtures.py::setup_dp (no DP code modified)."""
    sys.path.insert(0, str(DP_SRC))
    import diffusers  # noqa: F401  (before the wandb stub: diffusers probes find_spec('wandb'))
    import diffusers.optimization as dopt
    import diffusers.schedulers.scheduling_ddpm  # noqa: F401
    import diffusers.training_utils  # noqa: F401
    sys.modules.setdefault("wandb", types.ModuleType("wandb"))  # DP workspaces `import wandb` at module level
    # DP's lr_scheduler.py imports Union/Optional/Optimizer through diffusers.optimization (diffusers 0.11 re-exported)
    for n, v in (("Union", typing.Union), ("Optional", typing.Optional), ("Optimizer", torch.optim.Optimizer)):
        if not hasattr(dopt, n):
            setattr(dopt, n, v)
    from omegaconf import OmegaConf
    OmegaConf.register_new_resolver("eval", eval, replace=True)  # as DP's train.py


def compose(overrides):
    from hydra import compose as hcompose
    from hydra import initialize_config_dir
    from omegaconf import OmegaConf
    with initialize_config_dir(config_dir=str(DP_SRC / "diffusion_policy" / "config"), version_base=None):
        cfg = hcompose(config_name="train_diffusion_unet_lowdim_workspace", overrides=overrides)
    OmegaConf.resolve(cfg)  # as DP's train.py before building the workspace
    return cfg


OVERRIDES = [
    "task=pusht_lowdim",
    f"task.dataset.zarr_path={ZARR}",
    "policy.model.down_dims=[64,128,256]",  # CPU-sized (DP default [256,512,1024])
    "optimizer.lr=1.0e-3",                  # CPU budget (DP default 1e-4)
    "training.device=cpu",
    "dataloader.num_workers=0", "dataloader.pin_memory=False",          # one process on a shared 2-core box
    "val_dataloader.num_workers=0", "val_dataloader.pin_memory=False",
]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=6000, help="total optimizer steps (cosine schedule length)")
    ap.add_argument("--bench", type=float, default=0.0, help="only time the loop for this many seconds, save nothing")
    ap.add_argument("--ckpt-every", type=int, default=2000)
    ap.add_argument("--resume", action="store_true", help="continue from train_lowdim/checkpoints/latest.ckpt")
    args = ap.parse_args()

    torch.set_num_threads(1)
    setup_dp()
    import hydra
    from diffusion_policy.common.pytorch_util import dict_apply  # noqa: F401
    from diffusion_policy.dataset.base_dataset import BaseLowdimDataset
    from diffusion_policy.model.common.lr_scheduler import get_scheduler
    from torch.utils.data import DataLoader

    cfg = compose(OVERRIDES + [f"+training.total_steps_cpu={args.steps}"])
    cls = hydra.utils.get_class(cfg._target_)
    ws = cls(cfg, output_dir=str(OUT))  # seeds torch/np/random with cfg.training.seed (42)
    ckpt_dir = OUT / "checkpoints"
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    latest = ckpt_dir / "latest.ckpt"
    if args.resume and latest.is_file():
        ws.load_checkpoint(path=latest)
        print(f"resumed from {latest} at global_step {ws.global_step}", flush=True)

    dataset = hydra.utils.instantiate(cfg.task.dataset)
    assert isinstance(dataset, BaseLowdimDataset)
    train_dl = DataLoader(dataset, **cfg.dataloader)
    val_dl = DataLoader(dataset.get_validation_dataset(), **cfg.val_dataloader)
    normalizer = dataset.get_normalizer()
    ws.model.set_normalizer(normalizer)
    ws.ema_model.set_normalizer(normalizer)
    n_params = sum(p.numel() for p in ws.model.model.parameters())
    print(f"train samples {len(dataset)} ({int(dataset.train_mask.sum())} episodes), "
          f"val samples {len(val_dl.dataset)}, batches/epoch {len(train_dl)}, unet params {n_params}", flush=True)

    lr_scheduler = get_scheduler(cfg.training.lr_scheduler, optimizer=ws.optimizer,
                                 num_warmup_steps=cfg.training.lr_warmup_steps,
                                 num_training_steps=args.steps, last_epoch=ws.global_step - 1)
    ema = hydra.utils.instantiate(cfg.ema, model=ws.ema_model)
    ema.optimization_step = ws.global_step  # DP's EMAModel counts its own steps; restore it on resume

    log = open(Path(REPO / "runs/dp/train_loss.log"), "a")

    def val_loss():
        with torch.no_grad():
            ls = [ws.model.compute_loss(b).item() for b in val_dl]
        return float(np.mean(ls)) if ls else float("nan")

    def save(tag_path):
        ws.save_checkpoint(path=tag_path)
        if ws._saving_thread is not None:
            ws._saving_thread.join()

    t0 = time.time()
    ws.model.train()
    recent = []
    done = ws.global_step >= args.steps
    while not done:
        for batch in train_dl:
            raw_loss = ws.model.compute_loss(batch)
            raw_loss.backward()
            ws.optimizer.step()
            ws.optimizer.zero_grad()
            lr_scheduler.step()
            ema.step(ws.model)
            ws.global_step += 1
            recent.append(raw_loss.item())
            el = time.time() - t0
            if ws.global_step % 50 == 0:
                msg = {"step": ws.global_step, "epoch": ws.epoch, "loss50": float(np.mean(recent[-50:])),
                       "lr": lr_scheduler.get_last_lr()[0], "ema_decay": ema.decay, "elapsed_s": round(el, 1)}
                log.write(json.dumps(msg) + "\n")
                log.flush()
                print(json.dumps(msg), flush=True)
            if args.bench and el > args.bench:
                n = len(recent)
                print(json.dumps({"bench_steps": n, "bench_s": el, "steps_per_s": n / el}), flush=True)
                return
            if not args.bench and ws.global_step % args.ckpt_every == 0:
                vl = val_loss()
                ws.model.train()
                save(ckpt_dir / f"step_{ws.global_step:06d}.ckpt")
                save(latest)
                msg = {"step": ws.global_step, "val_loss": vl, "saved": str(latest), "elapsed_s": round(el, 1)}
                log.write(json.dumps(msg) + "\n")
                log.flush()
                print(json.dumps(msg), flush=True)
            if ws.global_step >= args.steps:
                done = True
                break
        ws.epoch += 1
    vl = val_loss()
    save(latest)
    msg = {"final_step": ws.global_step, "epoch": ws.epoch, "final_loss50": float(np.mean(recent[-50:])),
           "final_loss200": float(np.mean(recent[-200:])), "val_loss": vl,
           "wall_s": round(time.time() - t0, 1), "saved": str(latest)}
    log.write(json.dumps(msg) + "\n")
    log.flush()
    print(json.dumps(msg), flush=True)


if __name__ == "__main__":
    main()
