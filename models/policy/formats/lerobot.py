"""LeRobot ``DiffusionPolicy`` checkpoints (a ``save_pretrained`` directory) as gpc policies.

Three generations of files are read, without LeRobot (``docs/foreign_policies.md``):

- *processors* (LeRobot >= 0.4): ``config.json`` with ``type``, ``input_features`` and a
  ``normalization_mapping`` per feature type; statistics in ``policy_preprocessor*.safetensors``
  / ``policy_postprocessor*.safetensors``, named by ``policy_*processor.json``;
- *buffers* (0.1.x after January 2025 to 0.3.x): the same ``config.json``; statistics inside
  ``model.safetensors`` (``normalize_inputs.buffer_observation_state.min`` ...);
- *flat* (before 2025, the hub's first diffusion policies): no ``type``,
  ``input_shapes`` and per-key ``input_normalization_modes``; statistics in the weights.

Normalisation is LeRobot's: min-max to [-1, 1] (its ``eps`` where a range is empty; the
buffer generations add 1e-8 to every range), mean-std with ``std + 1e-8``, quantiles like
min-max, identity where no mode is given. Images arrive as uint8 and LeRobot reads them as
floats in [0, 1]: the 1/255 is folded into the image's map.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from gpc.datasets.errors import DataError
from gpc.datasets.jsonfile import read_json
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
from gpc.models.policy.formats.safetensors import read_safetensors
from gpc.models.policy.formats.weights import RESNET_RULES, UNET_RULES, feature_order, permute_film, rename, take

CONFIG, WEIGHTS = "config.json", "model.safetensors"
PRE, POST = "policy_preprocessor.json", "policy_postprocessor.json"
EPS = 1e-8  # LeRobot's normalisation epsilon
SUPPORTED = "diffusion"
MODES = ("MIN_MAX", "MEAN_STD", "IDENTITY", "QUANTILES", "QUANTILE10")
QUANTILE_STATS = {"MIN_MAX": ("min", "max"), "QUANTILES": ("q01", "q99"), "QUANTILE10": ("q10", "q90")}
BUFFER_PREFIXES = ("normalize_inputs.buffer_", "normalize_targets.buffer_", "unnormalize_outputs.buffer_")


def is_lerobot(path: Path) -> bool:
    return (path / CONFIG).is_file()


def _field(cfg: Mapping[str, Any], name: str, path: Path, default: Any = ..., kind: Any = None) -> Any:
    """``cfg[name]`` (or ``default``), checked to be of ``kind``; a bad one is one line naming the file."""
    if name not in cfg or cfg[name] is None and default is not ...:
        if default is ...:
            raise DataError(f"{path}: config.json has no {name!r}")
        return default
    value = cfg[name]
    if kind is not None and not isinstance(value, kind) or isinstance(value, bool) and kind in (int, float, (int, float)):
        raise DataError(f"{path}: config.json field {name!r} is {value!r}, not a {getattr(kind, '__name__', kind)}")
    return value


def _kind_from_name(name: str) -> str:
    if name == "action":
        return "ACTION"
    if name.startswith("observation.image"):
        return "VISUAL"
    if name == "observation.environment_state":
        return "ENV"
    if name.startswith("observation.state"):
        return "STATE"
    return ""


def _features(cfg: Mapping[str, Any], path: Path) -> tuple[dict[str, tuple[str, tuple[int, ...]]], dict[str, str], str]:
    """{feature: (type, shape)} for inputs and the action, {feature: normalisation mode}, and the generation."""
    features: dict[str, tuple[str, tuple[int, ...]]] = {}
    modes: dict[str, str] = {}
    if "input_features" in cfg:
        generation = "buffers"
        for group in ("input_features", "output_features"):
            entries = _field(cfg, group, path, kind=dict)
            for name, entry in entries.items():
                if not isinstance(entry, dict) or "type" not in entry or "shape" not in entry:
                    raise DataError(f"{path}: config.json {group}.{name} needs a type and a shape")
                features[name] = (str(entry["type"]).upper(), _shape(entry["shape"], f"{group}.{name}", path))
        mapping = _field(cfg, "normalization_mapping", path, {}, dict)
        modes = {name: str(mapping.get(kind, "IDENTITY")).upper() for name, (kind, _) in features.items()}
    elif "input_shapes" in cfg:
        generation = "flat"
        for group in ("input_shapes", "output_shapes"):
            for name, shape in _field(cfg, group, path, kind=dict).items():
                kind = _kind_from_name(name)
                if not kind:
                    raise DataError(f"{path}: config.json {group} names {name!r}, whose kind (state, image, "
                                    "environment state) gpc cannot tell")
                features[name] = (kind, _shape(shape, f"{group}.{name}", path))
        for group in ("input_normalization_modes", "output_normalization_modes"):
            for name, mode in _field(cfg, group, path, {}, dict).items():
                modes[name] = str(mode).upper()
        modes = {name: modes.get(name, "IDENTITY") for name in features}
    else:
        raise DataError(f"{path}: config.json has neither input_features nor input_shapes (not a LeRobot policy config)")
    for name, mode in modes.items():
        if mode not in MODES:
            raise DataError(f"{path}: config.json normalises {name!r} with {mode!r}; gpc reads {', '.join(MODES)}")
    return features, modes, generation


def _shape(value: Any, what: str, path: Path) -> tuple[int, ...]:
    if not isinstance(value, list) or not value or not all(isinstance(v, int) and v > 0 for v in value):
        raise DataError(f"{path}: config.json {what} has shape {value!r}, not a list of positive integers")
    return tuple(value)


def _processor_stats(directory: Path, modes: dict[str, str]) -> dict[str, dict[str, np.ndarray]] | None:
    """Statistics from the processor files (and their modes, which take precedence), or None without them."""
    stats: dict[str, dict[str, np.ndarray]] = {}
    found = False
    for name, step_name in ((PRE, "normalizer_processor"), (POST, "unnormalizer_processor")):
        pipeline = directory / name
        if not pipeline.is_file():
            continue
        found = True
        document = read_json(pipeline)
        steps = document.get("steps", []) if isinstance(document, dict) else []
        for step in steps:
            if not isinstance(step, dict) or step.get("registry_name") != step_name:
                continue
            norm_map = (step.get("config") or {}).get("norm_map") or {}
            features = (step.get("config") or {}).get("features") or {}
            for feature, entry in features.items():
                if feature in modes and isinstance(entry, dict) and "type" in entry:
                    modes[feature] = str(norm_map.get(str(entry["type"]).upper(), "IDENTITY")).upper()
            state_file = step.get("state_file")
            if not state_file:
                raise DataError(f"{pipeline}: the {step_name} step names no state_file with its statistics")
            for key, tensor in read_safetensors(directory / state_file).items():
                feature, _, stat = key.rpartition(".")
                stats.setdefault(feature, {})[stat] = tensor.double().numpy()
    return stats if found else None


def _buffer_stats(weights: dict[str, torch.Tensor], features: Mapping[str, Any]) -> dict[str, dict[str, np.ndarray]]:
    """Statistics kept in the weights by LeRobot <= 0.3 (``normalize_inputs.buffer_observation_state.min``)."""
    by_buffer = {name.replace(".", "_"): name for name in features}
    stats: dict[str, dict[str, np.ndarray]] = {}
    order = {prefix: i for i, prefix in enumerate(BUFFER_PREFIXES)}  # unnormalize_outputs' action statistics last
    buffers = sorted((k for k in weights if k.startswith(BUFFER_PREFIXES)), key=lambda k: order[k.split("buffer_")[0] + "buffer_"])
    for key in buffers:
        tensor = weights.pop(key)
        rest = key.split(".buffer_", 1)[1]
        buffer, _, stat = rest.rpartition(".")
        if buffer in by_buffer:
            stats.setdefault(by_buffer[buffer], {})[stat] = tensor.double().numpy()
    return stats


def _affine(name: str, mode: str, stats: Mapping[str, np.ndarray], legacy: bool, inverse: bool,
            path: Path) -> tuple[np.ndarray, np.ndarray]:
    """LeRobot's map of feature ``name`` as ``x * scale + offset`` (``inverse``: the unnormalisation's inverse)."""
    def stat(s: str) -> np.ndarray:
        if s not in stats:
            raise DataError(f"{path}: {name!r} is normalised with {mode} but its {s!r} statistic is missing "
                            "(processor safetensors or normalize_* buffers)")
        value = np.asarray(stats[s], dtype=np.float64).reshape(-1)
        if not np.all(np.isfinite(value)):
            raise DataError(f"{path}: the {s!r} statistic of {name!r} is not finite (an untrained normaliser?)")
        return value

    if mode == "MEAN_STD":
        std = stat("std") if inverse else stat("std") + EPS
        scale = 1.0 / std
        return scale, -stat("mean") * scale
    if mode in QUANTILE_STATS:
        lo_name, hi_name = QUANTILE_STATS[mode]
        lo, hi = stat(lo_name), stat(hi_name)
        denom = hi - lo
        if legacy and not inverse:
            denom = denom + EPS
        elif not legacy:
            denom = np.where(denom == 0, EPS, denom)
        scale = 2.0 / denom
        return scale, -1.0 - scale * lo
    return np.ones(1), np.zeros(1)


def _image_affine(scale: np.ndarray, offset: np.ndarray, channels: int) -> tuple[np.ndarray, np.ndarray]:
    """A map of [0, 1] images (per channel or one for all) as one of uint8 images, per channel, channels last."""
    scale, offset = np.broadcast_to(scale, (channels,)), np.broadcast_to(offset, (channels,))
    return scale / IMAGE_RANGE, offset.copy()


def load(directory: Path, sources: Mapping[str, FeatureSource], task: str) -> Imported:
    """Read a LeRobot diffusion policy directory for ``task`` (whose observations ``sources`` name)."""
    path = directory / CONFIG
    cfg = read_json(path)
    if not isinstance(cfg, dict):
        raise DataError(f"{path}: not a JSON object")
    kind = cfg.get("type", SUPPORTED if "down_dims" in cfg else None)
    if kind != SUPPORTED:
        raise DataError(f"{path}: policy type {kind!r} is not supported (gpc plans with diffusion policies: LeRobot "
                        "'diffusion' or a Diffusion Policy .ckpt)")
    features, modes, generation = _features(cfg, path)
    inputs = {n: f for n, f in features.items() if f[0] != "ACTION"}
    if "action" not in features:
        raise DataError(f"{path}: config.json has no 'action' output feature")
    action_dim = int(np.prod(features["action"][1]))
    weights_file = directory / WEIGHTS
    if not weights_file.is_file():
        raise DataError(f"{weights_file}: missing (a LeRobot policy directory holds config.json and model.safetensors)")
    weights = {k.replace("._orig_mod.", ".").replace("_orig_mod.", ""): v for k, v in read_safetensors(weights_file).items()}
    stats = _processor_stats(directory, modes)
    buffers = _buffer_stats(weights, features)
    if stats is None:
        stats = buffers
    else:
        generation = "processors"
    legacy = generation != "processors"

    images = [n for n, (k, _) in inputs.items() if k == "VISUAL"]
    states = [n for n, (k, _) in inputs.items() if k == "STATE"]
    envs = [n for n, (k, _) in inputs.items() if k == "ENV"]
    others = [n for n, (k, _) in inputs.items() if k not in ("VISUAL", "STATE", "ENV")]
    if others or len(images) > 1 or len(states) != 1 or len(envs) > 1 or bool(images) == bool(envs):
        raise DataError(f"{path}: inputs {', '.join(f'{n} ({k})' for n, (k, _) in inputs.items())}: gpc reads LeRobot "
                        "policies of one STATE feature with either one camera (VISUAL) or one ENV feature")
    state_name = states[0]
    state_src = source_for(sources, state_name, str(directory), task)
    check_width(state_src, state_name, int(np.prod(inputs[state_name][1])), str(directory), task)
    if state_src.shape is None:
        raise DataError(f"{directory}: task {task!r} gives no fixed shape for {state_src.key!r}")

    normalizer = MinMaxNormalizer()
    normalizer.add_affine(state_src.key, *padded(state_src, *_affine(state_name, modes[state_name], stats.get(state_name, {}),
                                                                      legacy, False, path)))
    scale, offset = _affine("action", modes["action"], stats.get("action", {}), legacy, True, path)
    normalizer.add_affine("action", np.broadcast_to(scale, (action_dim,)).copy(), np.broadcast_to(offset, (action_dim,)).copy())

    unet_weights = rename(take(weights, "diffusion.unet."), UNET_RULES, "unet.")
    n_obs = int(_field(cfg, "n_obs_steps", path, kind=int))
    step_dim = int(_field(cfg, "diffusion_step_embed_dim", path, 128, int))
    state_width = int(np.prod(inputs[state_name][1]))
    encoder_kw: dict[str, Any]
    if images:
        name = images[0]
        src = source_for(sources, name, str(directory), task)
        c, h, w = inputs[name][1]
        crop = cfg.get("crop_shape")
        if cfg.get("resize_shape") is not None:
            raise DataError(f"{path}: resize_shape {cfg['resize_shape']} is not supported (gpc crops, it does not resize)")
        if str(cfg.get("vision_backbone", "resnet18")) != "resnet18":
            raise DataError(f"{path}: vision_backbone {cfg.get('vision_backbone')!r} is not supported (gpc has resnet18)")
        crop_size = h if crop is None else crop[0]
        if (crop is None and h != w) or (crop is not None and (len(crop) != 2 or crop[0] != crop[1])):
            raise DataError(f"{path}: crop_shape {crop} of {h}x{w} images: gpc crops square images only")
        prefix = "diffusion.rgb_encoder.0." if any(k.startswith("diffusion.rgb_encoder.0.") for k in weights) else "diffusion.rgb_encoder."
        encoder = take(weights, prefix)
        keypoints = int(_field(cfg, "spatial_softmax_num_keypoints", path, 32, int))
        group_norm = not any(k.endswith("running_mean") for k in encoder)
        encoder_weights = {
            **rename(take(encoder, "backbone."), RESNET_RULES, "encoder.parts.0.net.trunk."),
            **{f"encoder.parts.0.net.pool.to_maps.{k}": v for k, v in take(encoder, "pool.nets.").items()},
            **{f"encoder.parts.0.net.head.{k}": v for k, v in take(encoder, "out.").items()},
        }
        feature_dim = int(encoder["out.weight"].shape[0]) if "out.weight" in encoder else 2 * keypoints
        encoder_kw = dict(obs_type="image", obs_shapes=((src.key, (h, w, c)), (state_src.key, state_src.shape)),
                          crop_size=int(crop_size), resnet_width=64, spatial_keypoints=keypoints,
                          image_feature_dim=feature_dim, image_norm="group" if group_norm else "batch",
                          image_feature_relu=True)
        if src.key != "img":
            raise DataError(f"{directory}: task {task!r} has {name!r} under {src.key!r}; gpc's image policies read 'img'")
        s, o = _affine(name, modes[name], stats.get(name, {}), legacy, False, path)
        if modes[name] == "IDENTITY":
            s, o = np.ones(c), np.zeros(c)
        normalizer.add_affine(src.key, *_image_affine(s, o, c))
        parts = [("state", state_width), ("object", feature_dim)]
        used = {k for k in weights if k.startswith(prefix)}
    else:
        name = envs[0]
        src = source_for(sources, name, str(directory), task)
        width = int(np.prod(inputs[name][1]))
        check_width(src, name, width, str(directory), task)
        assert src.shape is not None  # check_width knows the width
        encoder_kw = dict(obs_type="keypoints", keypoint_key=src.key, obs_shapes=((src.key, src.shape), (state_src.key, state_src.shape)))
        normalizer.add_affine(src.key, *padded(src, *_affine(name, modes[name], stats.get(name, {}), legacy, False, path)))
        encoder_weights, parts, used = {}, [("state", state_width), ("object", width)], set()
        feature_dim = width
    encoder_kw["agent_dims"] = state_width
    unet_weights = {**unet_weights, **encoder_weights}
    leftover = [k for k in weights if not k.startswith("diffusion.unet.") and k not in used]
    if leftover:
        raise DataError(f"{weights_file}: the weights do not match the config: {len(leftover)} unexpected (first: {leftover[0]})")

    scheduler = str(_field(cfg, "noise_scheduler_type", path, "DDPM", str)).upper()
    if scheduler not in ("DDPM", "DDIM"):
        raise DataError(f"{path}: noise_scheduler_type {scheduler!r}: gpc samples with DDPM or DDIM")
    schedule = str(_field(cfg, "beta_schedule", path, "squaredcos_cap_v2", str))
    prediction = str(_field(cfg, "prediction_type", path, "epsilon", str))
    if schedule not in BETA_SCHEDULES or prediction not in PREDICTIONS:
        raise DataError(f"{path}: beta_schedule {schedule!r} / prediction_type {prediction!r}: gpc has "
                        f"{', '.join(BETA_SCHEDULES)} / {', '.join(PREDICTIONS)}")
    train_steps = int(_field(cfg, "num_train_timesteps", path, 100, int))
    clip = float(_field(cfg, "clip_sample_range", path, 1.0, (int, float))) if _field(cfg, "clip_sample", path, True, bool) else 0.0

    def make() -> PolicyConfig:
        return PolicyConfig(
            task=task, action_dim=action_dim, horizon=int(_field(cfg, "horizon", path, kind=int)), n_obs_steps=n_obs,
            n_action_steps=int(_field(cfg, "n_action_steps", path, kind=int)),
            encoder=EncoderConfig(**encoder_kw),
            unet=UNetConfig(down_dims=tuple(int(d) for d in _field(cfg, "down_dims", path, kind=list)),
                            kernel_size=int(_field(cfg, "kernel_size", path, 5, int)),
                            n_groups=int(_field(cfg, "n_groups", path, 8, int)), step_embed_dim=step_dim,
                            cond_predict_scale=bool(_field(cfg, "use_film_scale_modulation", path, True, bool)), final_groups=8),
            noise=NoiseConfig(train_steps=train_steps, beta_schedule=schedule, clip_sample=clip, prediction=prediction,
                              beta_start=float(_field(cfg, "beta_start", path, 1e-4, (int, float))),
                              beta_end=float(_field(cfg, "beta_end", path, 0.02, (int, float)))),
            sampler=SamplerConfig(scheduler.lower(), int(_field(cfg, "num_inference_steps", path, train_steps, int))),
        )

    config = checked_config(make, str(path))  # before the weights are read by it: n_obs_steps 0 is named here
    permute_film(unet_weights, step_dim, n_obs, feature_order(parts, ["object", "state"]), str(path))
    source = {
        "format": "lerobot", "generation": generation, "policy_type": SUPPORTED,
        "features": {n: {"type": k, "shape": list(s), "normalization": modes[n],
                         "from": "action" if k == "ACTION" else _describe(sources[n])} for n, (k, s) in features.items()},
    }
    return Imported(config, normalizer, unet_weights, None, source)


def _describe(source: FeatureSource) -> str:
    return source.key if source.take is None else f"{source.key}[:{source.take}]"
