"""bf16 only where the hardware computes it (``gpc.models.networks.precision``): emulated bf16 is slower than float32."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from test_visual_world_model import _windows, make_store, run, tiny

import gpc.models.networks.precision as precision
import gpc.models.training.trainer as trainer
from gpc.models.training.config import RunConfig
from gpc.models.training.trainer import train
from gpc.models.world_models.module import WorldModelModule

pytestmark = pytest.mark.usefixtures("one_thread")


def test_bf16_rolls_out_only_where_the_hardware_computes_it(tmp_path, monkeypatch):
    """A bf16 model rolls out in float32 where bf16 would be emulated (4-6x slower on an AVX2 CPU), under bf16
    autocast where it is native, unless a planner pins the precision; training's ``--precision bf16-auto`` follows
    the same test."""
    store = make_store(tmp_path / "frames.zarr", episodes=3)
    model = train(WorldModelModule, tiny(1), [store], run(tmp_path, "vwm", max_steps=4)).module.eval()
    hist, acts = _windows(store, model)
    with torch.no_grad():
        fp32 = model.rollout(hist, acts)
        model.dynamics.config = dataclasses.replace(model.dynamics.config, bf16=True)
        monkeypatch.setattr(precision, "native_bf16", lambda device: False)
        assert torch.equal(model.rollout(hist, acts), fp32) and model.set_rollout_precision("bf16-auto") == "float32"
        monkeypatch.setattr(precision, "native_bf16", lambda device: True)
        assert not torch.equal(model.rollout(hist, acts), fp32) and model.set_rollout_precision("bf16-auto") == "bfloat16"
        # a planner pins float32 (the same numbers on every machine) or asks for bf16 where it is emulated
        assert model.set_rollout_precision("32-true") == "float32" and torch.equal(model.rollout(hist, acts), fp32)
        monkeypatch.setattr(precision, "native_bf16", lambda device: False)
        assert model.set_rollout_precision("bf16-mixed") == "bfloat16" and not torch.equal(model.rollout(hist, acts), fp32)
    with pytest.raises(ValueError, match="--precision 'fp16': use one of bf16-auto, 32-true, bf16-mixed"):
        model.set_rollout_precision("fp16")
    for native, expected in ((False, "32-true"), (True, "bf16-mixed")):
        monkeypatch.setattr(trainer, "native_bf16", lambda device, native=native: native)
        auto = RunConfig(run_dir="unused", max_steps=1, precision="bf16-auto", accelerator="cpu")
        assert trainer.resolve_precision(auto).precision == expected
    assert trainer.resolve_precision(dataclasses.replace(auto, precision="bf16-mixed")).precision == "bf16-mixed"  # as asked
