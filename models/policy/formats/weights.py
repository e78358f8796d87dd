"""Other frameworks' Diffusion Policy weights -> gpc's network, by renaming and one column permutation.

LeRobot's and Diffusion Policy's U-Nets and ResNet18 encoders are gpc's networks under other
names (``docs/foreign_policies.md`` has the table). What differs beyond names is the order of
the per-step observation features in the conditioning vector: gpc puts the object (image
features or keypoints) before the agent's position, LeRobot the other way round. The FiLM
layers are the only ones that read that vector, so permuting their input columns once gives
the same function, and the policy then runs as any gpc policy.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable, Mapping, Sequence

import torch
from torch import nn

from gpc.datasets.errors import DataError

Rules = Sequence[tuple[str, str | Callable[[re.Match[str]], str]]]  # (regular expression, replacement), in order

UNET_RULES: Rules = (  # LeRobot's and Diffusion Policy's DiffusionConditionalUnet1d / ConditionalUnet1D
    (r"^diffusion_step_encoder\.1\.", "step_mlp.0."),
    (r"^diffusion_step_encoder\.3\.", "step_mlp.2."),
    (r"^down_modules\.", "down."),
    (r"^mid_modules\.", "mid."),
    (r"^up_modules\.", "up."),
    (r"\.blocks\.0\.block\.", ".conv1."),  # Diffusion Policy
    (r"\.blocks\.1\.block\.", ".conv2."),
    (r"\.conv([12])\.block\.", r".conv\1."),  # LeRobot
    (r"^(down|up)\.(\d+)\.2\.conv\.", r"\1.\2.2."),  # Diffusion Policy's Downsample1d / Upsample1d wrappers
    (r"\.cond_encoder\.1\.", ".film.1."),
    (r"\.residual_conv\.", ".skip."),
    (r"^final_conv\.0\.block\.", "final.0."),
    (r"^final_conv\.1\.", "final.1."),
)
RESNET_RULES: Rules = (  # torchvision resnet18's children[:-2] as an nn.Sequential (LeRobot; robomimic's ResNet18Conv)
    (r"^([01])\.", r"stem.\1."),
    (r"^([4-7])\.", lambda m: f"stages.{int(m.group(1)) - 4}."),
    (r"\.bn([12])\.", r".norm\1."),
    (r"\.downsample\.", ".project."),
)


def rename(state: Mapping[str, torch.Tensor], rules: Rules, prefix: str = "") -> dict[str, torch.Tensor]:
    """Every key through every rule, then ``prefix`` in front."""
    out = {}
    for key, value in state.items():
        for pattern, repl in rules:
            key = re.sub(pattern, repl, key)
        out[prefix + key] = value
    return out


def take(state: Mapping[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    """The entries under ``prefix``, with it removed."""
    return {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}


def permute_film(state: dict[str, torch.Tensor], step_dim: int, n_obs_steps: int, order: Sequence[int], where: str) -> None:
    """Reorder each FiLM layer's observation columns in place: gpc's feature ``j`` of every step is
    the source's feature ``order[j]`` (the diffusion-step embedding's ``step_dim`` columns stay first).
    ``where``: the file whose config gives ``n_obs_steps``, named by a mismatch."""
    width = len(order)
    columns = list(range(step_dim)) + [step_dim + s * width + j for s in range(n_obs_steps) for j in order]
    index = torch.tensor(columns)
    for key in [k for k in state if k.endswith("film.1.weight")]:
        weight = state[key]
        if weight.shape[1] != len(columns):
            raise DataError(f"{where}: FiLM layer {key} reads {weight.shape[1]} features, the config gives "
                            f"{step_dim} + {n_obs_steps} x {width}")
        state[key] = weight[:, index]


def feature_order(source: Iterable[tuple[str, int]], ours: Iterable[str]) -> list[int]:
    """Column ``j`` of our per-step features -> its column in the source's, parts given as (name, width)."""
    starts, at = {}, 0
    widths = dict(source)
    for name, width in widths.items():
        starts[name] = at
        at += width
    return [starts[name] + i for name in ours for i in range(widths[name])]


def load_exact(module: nn.Module, state: Mapping[str, torch.Tensor], source: str) -> None:
    """Load ``state`` into ``module`` only if every key and shape matches; else one ``DataError`` naming ``source``."""
    want = module.state_dict()
    missing = [k for k in want if k not in state]
    extra = [k for k in state if k not in want]
    if missing or extra:
        parts = []
        if missing:
            parts.append(f"{len(missing)} missing (first: {missing[0]})")
        if extra:
            parts.append(f"{len(extra)} unexpected (first: {extra[0]})")
        raise DataError(f"{source}: the weights do not match the config: {', '.join(parts)}")
    for key, value in want.items():
        if tuple(state[key].shape) != tuple(value.shape):
            raise DataError(f"{source}: the weights do not match the config: {key} is {tuple(state[key].shape)}, "
                            f"the config builds {tuple(value.shape)}")
    module.load_state_dict({k: v.to(want[k].dtype) for k, v in state.items()}, strict=True)
