"""Diffusion Policy (real-stanford) ``.ckpt`` files as gpc policies.

A checkpoint holds the run's resolved Hydra config (``cfg``) and ``state_dicts`` (``model``,
``ema_model``, ``optimizer``); it is read by the restricted unpickler, so a crafted file runs
nothing. Two policy classes are read: ``DiffusionUnetLowdimPolicy`` (Push-T's 20-d ``obs``:
the 9 keypoints, then the agent's position) and ``DiffusionUnetHybridImagePolicy`` (robomimic's
ResNet18 encoder of ``image``, a ReLU on its features, then ``agent_pos``). The EMA weights are the ones sampled, as
Diffusion Policy's evaluation does, when the run kept them. Its ``LinearNormalizer`` already is
an affine map per feature (``x * scale + offset``), which gpc's normaliser takes as it is.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from gpc.datasets.errors import DataError
from gpc.datasets.normalizer import MinMaxNormalizer
from gpc.models.networks.ddpm import BETA_SCHEDULES, PREDICTIONS, NoiseConfig, SamplerConfig
from gpc.models.networks.encoders import EncoderConfig
from gpc.models.networks.unet1d import UNetConfig
from gpc.models.policy.config import PolicyConfig
from gpc.models.policy.formats.common import (
    IMAGE_RANGE,
    FeatureSource,
    Imported,
    check_width,
    checked_config,
    padded,
    source_for,
)
from gpc.models.policy.formats.restricted_pickle import load_restricted, plain
from gpc.models.policy.formats.weights import RESNET_RULES, UNET_RULES, feature_order, permute_film, rename, take

LOWDIM, HYBRID = "DiffusionUnetLowdimPolicy", "DiffusionUnetHybridImagePolicy"
SCHEDULERS = {"DDPMScheduler": "ddpm", "DDIMScheduler": "ddim"}


def is_checkpoint(payload: Any) -> bool:
    return isinstance(payload, dict) and "cfg" in payload and isinstance(payload.get("state_dicts"), dict)


def _get(cfg: Mapping[str, Any], dotted: str, path: Path, default: Any = ...) -> Any:
    node: Any = cfg
    for part in dotted.split("."):
        if not isinstance(node, Mapping) or part not in node:
            if default is ...:
                raise DataError(f"{path}: the checkpoint's config has no {dotted!r}")
            return default
        node = node[part]
    return node


def _affine(state: Mapping[str, torch.Tensor], key: str, path: Path) -> tuple[np.ndarray, np.ndarray]:
    names = (f"normalizer.params_dict.{key}.scale", f"normalizer.params_dict.{key}.offset")
    if not all(n in state for n in names):
        raise DataError(f"{path}: the checkpoint's normaliser has no {key!r} statistics ({names[0]})")
    return state[names[0]].double().numpy().reshape(-1), state[names[1]].double().numpy().reshape(-1)


def _noise(policy: Mapping[str, Any], path: Path) -> tuple[NoiseConfig, SamplerConfig]:
    sched = _get(policy, "noise_scheduler", path)
    kind = SCHEDULERS.get(str(sched.get("_target_", "")).rsplit(".", 1)[-1])
    if kind is None:
        raise DataError(f"{path}: noise scheduler {sched.get('_target_')!r}: gpc samples with DDPMScheduler or DDIMScheduler")
    if kind == "ddpm" and sched.get("variance_type", "fixed_small") != "fixed_small":
        raise DataError(f"{path}: DDPM variance_type {sched.get('variance_type')!r}: gpc has fixed_small")
    if kind == "ddim" and (not sched.get("set_alpha_to_one", True) or sched.get("steps_offset", 0)):
        raise DataError(f"{path}: DDIM with set_alpha_to_one False or a steps_offset is not supported")
    schedule, prediction = sched.get("beta_schedule", "linear"), sched.get("prediction_type", "epsilon")
    if schedule not in BETA_SCHEDULES or prediction not in PREDICTIONS:
        raise DataError(f"{path}: beta_schedule {schedule!r} / prediction_type {prediction!r}: gpc has "
                        f"{', '.join(BETA_SCHEDULES)} / {', '.join(PREDICTIONS)}")
    steps = int(sched.get("num_train_timesteps", 1000))
    noise = NoiseConfig(train_steps=steps, beta_schedule=schedule, prediction=prediction,
                        clip_sample=1.0 if sched.get("clip_sample", True) else 0.0,
                        beta_start=float(sched.get("beta_start", 1e-4)), beta_end=float(sched.get("beta_end", 0.02)))
    inference = policy.get("num_inference_steps") or steps
    return noise, SamplerConfig(kind, int(inference))


def _unet(policy: Mapping[str, Any], path: Path) -> UNetConfig:
    model = policy.get("model")
    net: Mapping[str, Any] = model if isinstance(model, Mapping) else policy
    return UNetConfig(down_dims=tuple(int(d) for d in _get(net, "down_dims", path)),
                      kernel_size=int(net.get("kernel_size", 5)), n_groups=int(net.get("n_groups", 8)),
                      step_embed_dim=int(net.get("diffusion_step_embed_dim", 256)),
                      cond_predict_scale=bool(net.get("cond_predict_scale", False)), final_groups=8)


def load(path: Path, sources: Mapping[str, FeatureSource], task: str) -> Imported:
    """Read a Diffusion Policy checkpoint for ``task`` (whose observations ``sources`` name)."""
    payload = load_restricted(path)
    if not is_checkpoint(payload):
        raise DataError(f"{path}: not a Diffusion Policy checkpoint (no cfg and state_dicts)")
    cfg = plain(payload["cfg"])
    if not isinstance(cfg, dict):
        raise DataError(f"{path}: the checkpoint's cfg is not a config")
    policy = _get(cfg, "policy", path)
    cls = str(policy.get("_target_", "")).rsplit(".", 1)[-1]
    if cls not in (LOWDIM, HYBRID):
        raise DataError(f"{path}: policy class {policy.get('_target_')!r} is not supported (gpc reads {LOWDIM} and {HYBRID})")
    if not policy.get("obs_as_global_cond", True) or policy.get("obs_as_local_cond", False):
        raise DataError(f"{path}: the policy conditions by inpainting or local conditioning; gpc reads obs_as_global_cond policies")
    if policy.get("pred_action_steps_only", False):
        raise DataError(f"{path}: pred_action_steps_only policies are not supported")
    if cls == LOWDIM and not policy.get("oa_step_convention", False):
        raise DataError(f"{path}: oa_step_convention False (actions executed from index n_obs_steps) is not supported")
    states = payload["state_dicts"]
    use_ema = bool(_get(cfg, "training.use_ema", path, False)) and "ema_model" in states
    model_state, ema_state = states.get("model"), states.get("ema_model") if use_ema else None
    if not isinstance(model_state, dict):
        raise DataError(f"{path}: the checkpoint has no model weights (state_dicts.model)")
    n_obs = int(_get(policy, "n_obs_steps", path))
    unet = _unet(policy, path)
    noise, sampler = _noise(policy, path)
    normalizer = MinMaxNormalizer()
    normal_state = ema_state if ema_state is not None else model_state
    action_scale, action_offset = _affine(normal_state, "action", path)
    normalizer.add_affine("action", action_scale, action_offset)
    agent = source_for(sources, "agent_pos", str(path), task)
    if agent.shape is None:
        raise DataError(f"{path}: task {task!r} gives no fixed shape for {agent.key!r}")
    agent_width = agent.width or 0

    if cls == LOWDIM:
        keypoint = source_for(sources, "keypoint", str(path), task)
        kp_width = keypoint.width or 0
        obs_dim = int(policy.get("obs_dim", _get(cfg, "obs_dim", path)))
        if obs_dim != kp_width + agent_width:
            raise DataError(f"{path}: the policy reads a {obs_dim}-d obs; task {task!r} provides {kp_width} keypoint "
                            f"values + {agent_width} agent values = {kp_width + agent_width}")
        scale, offset = _affine(normal_state, "obs", path)
        assert keypoint.shape is not None
        normalizer.add_affine(keypoint.key, scale[:kp_width].reshape(keypoint.shape), offset[:kp_width].reshape(keypoint.shape))
        normalizer.add_affine(agent.key, *padded(agent, scale[kp_width:], offset[kp_width:]))
        encoder = EncoderConfig("keypoints", keypoint_key=keypoint.key, agent_dims=agent_width,
                                obs_shapes=((keypoint.key, keypoint.shape), (agent.key, agent.shape)))
        action_dim = int(policy.get("action_dim", _get(cfg, "action_dim", path)))

        def convert(state: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
            return rename(take(state, "model."), UNET_RULES, "unet.")
    else:
        meta = _get(policy, "shape_meta", path)
        obs_meta = _get(meta, "obs", path)
        rgb = [k for k, v in obs_meta.items() if isinstance(v, Mapping) and v.get("type") == "rgb"]
        low = [k for k, v in obs_meta.items() if isinstance(v, Mapping) and v.get("type", "low_dim") == "low_dim"]
        if len(rgb) != 1 or low != ["agent_pos"]:
            raise DataError(f"{path}: the policy reads {', '.join(obs_meta)}; gpc reads one camera and agent_pos")
        image = rgb[0]
        img_src = source_for(sources, image, str(path), task)
        check_width(agent, "agent_pos", int(np.prod(obs_meta["agent_pos"]["shape"])), str(path), task)
        c, h, w = (int(v) for v in obs_meta[image]["shape"])
        crop = policy.get("crop_shape")
        if crop is not None and (len(crop) != 2 or crop[0] != crop[1]):
            raise DataError(f"{path}: crop_shape {crop}: gpc crops square images only")
        if crop is not None and not policy.get("eval_fixed_crop", False):
            raise DataError(f"{path}: eval_fixed_crop False (random crops at evaluation) is not supported")
        prefix = f"obs_encoder.obs_nets.{image}."
        net = take(normal_state, prefix)
        if "pool.temperature" in net and abs(float(net["pool.temperature"].reshape(-1)[0]) - 1.0) > 1e-6:
            raise DataError(f"{path}: a spatial-softmax temperature other than 1 is not supported")
        if "nets.3.weight" not in net or "pool.nets.weight" not in net:
            raise DataError(f"{path}: the image encoder's weights are not robomimic's VisualCore ({prefix}nets.3, pool.nets)")
        feature_dim, keypoints = int(net["nets.3.weight"].shape[0]), int(net["pool.nets.weight"].shape[0])
        encoder = EncoderConfig("image", obs_shapes=((img_src.key, (h, w, c)), (agent.key, agent.shape)), agent_dims=agent_width,
                                crop_size=int(crop[0]) if crop else h, resnet_width=64, spatial_keypoints=keypoints,
                                image_feature_dim=feature_dim, image_norm="group" if policy.get("obs_encoder_group_norm") else "batch",
                                image_feature_relu=True)  # robomimic's ObservationEncoder applies a ReLU after each net
        scale, offset = _affine(normal_state, image, path)
        normalizer.add_affine(img_src.key, np.broadcast_to(scale, (c,)) / IMAGE_RANGE, np.broadcast_to(offset, (c,)).copy())
        normalizer.add_affine(agent.key, *padded(agent, *_affine(normal_state, "agent_pos", path)))
        action_dim = int(np.prod(_get(meta, "action.shape", path)))
        widths = [(k, feature_dim if k == image else agent_width) for k in obs_meta]
        order = feature_order(widths, [image, "agent_pos"])

        def convert(state: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
            enc = take(state, prefix)
            out = {
                **rename(take(state, "model."), UNET_RULES, "unet."),
                **rename(take(enc, "backbone.nets."), RESNET_RULES, "encoder.parts.0.net.trunk."),
                **{f"encoder.parts.0.net.pool.to_maps.{k}": v for k, v in take(enc, "pool.nets.").items()},
                **{f"encoder.parts.0.net.head.{k}": v for k, v in take(enc, "nets.3.").items()},
            }
            permute_film(out, unet.step_embed_dim, n_obs, order, str(path))
            return out

    def make() -> PolicyConfig:
        return PolicyConfig(task=task, action_dim=action_dim, horizon=int(_get(policy, "horizon", path)), n_obs_steps=n_obs,
                            n_action_steps=int(_get(policy, "n_action_steps", path)), encoder=encoder, unet=unet,
                            noise=noise, sampler=sampler)

    config = checked_config(make, str(path))
    source = {"format": "diffusion_policy", "policy_class": cls, "weights": "ema_model" if ema_state is not None else "model",
              "features": _features(cls, policy, sources)}
    return Imported(config, normalizer, convert(model_state), convert(ema_state) if ema_state is not None else None, source)


def _features(cls: str, policy: Mapping[str, Any], sources: Mapping[str, FeatureSource]) -> dict[str, Any]:
    def where(name: str) -> str:
        src = sources[name]
        return src.key if src.take is None else f"{src.key}[:{src.take}]"

    if cls == LOWDIM:
        return {"obs": {"shape": [policy.get("obs_dim")], "from": f"{where('keypoint')} + {where('agent_pos')}"}}
    return {k: {"shape": list(v.get("shape", [])), "from": where(k)} for k, v in policy["shape_meta"]["obs"].items()}
