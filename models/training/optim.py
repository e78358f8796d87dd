"""The one optimiser recipe every module trains with: AdamW and a per-step cosine schedule after warm-up."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import Any

import torch


def cosine_with_warmup(warmup: int, total: int) -> Callable[[int], float]:
    """Learning-rate factor: linear 0 -> 1 over ``warmup`` steps, then half a cosine to 0 at ``total``."""

    def factor(step: int) -> float:
        if step < warmup:
            return step / max(1, warmup)
        progress = min(1.0, (step - warmup) / max(1, total - warmup))
        return max(0.0, 0.5 * (1.0 + math.cos(math.pi * progress)))

    return factor


def adamw_cosine(params: Iterable[torch.nn.Parameter], optim: Any, trainer: Any) -> dict[str, Any]:
    """Lightning's ``configure_optimizers`` answer for an ``OptimConfig`` (lr, betas, weight_decay, warmup_steps);
    the cosine reaches 0 at the trainer's last step."""
    trainable = [p for p in params if p.requires_grad]
    optimizer = torch.optim.AdamW(trainable, lr=optim.lr, betas=optim.betas, weight_decay=optim.weight_decay)
    total = trainer.estimated_stepping_batches
    total = int(total) if math.isfinite(total) else 10**12
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, cosine_with_warmup(optim.warmup_steps, total))
    return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}
