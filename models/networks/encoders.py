"""Observation encoders: one interface, built from per-key parts, for every observation type.

An observation type names the data keys it reads and how each becomes features:

=========  =========================  ===============================================
obs type   data keys                  features per step
=========  =========================  ===============================================
state      state                      the normalised state vector
keypoints  keypoint, state            flattened keypoints + agent position
image      img, state                 ResNet18 spatial-softmax features + agent position
=========  =========================  ===============================================

The keypoints type reads ``keypoint`` unless ``keypoint_key`` names another vector of object
points (a policy trained elsewhere may read, say, the object's outline vertices).

With ``goal=True`` (a goal that varies per episode, GPC's random-goal variant) the encoder
also reads the goal: its pose (``goal``) for state observations, its keypoints
(``goal_keypoint``) for keypoint ones; images show the goal drawn in the scene already.

The agent position is the first ``agent_dims`` entries of ``state``. Inputs arrive
normalised (``MinMaxNormalizer``) with shapes ``(B, T, *step_shape)``; images are
``(B, T, H, W, C)`` in [-1, 1]. Images are randomly cropped in training mode and
centre-cropped in evaluation mode.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
import torch
from torch import nn

from gpc.datasets.errors import DataError
from gpc.models.networks.resnet import NORMS, ResNet18Keypoints

OBS_KEYS: dict[str, tuple[str, ...]] = {
    "state": ("state",),
    "keypoints": ("keypoint", "state"),
    "image": ("img", "state"),
}
GOAL_KEYS: dict[str, tuple[str, ...]] = {"state": ("goal",), "keypoints": ("goal_keypoint",), "image": ()}


@dataclass(frozen=True)
class EncoderConfig:
    """Which observation type to encode, the data's step shapes, and the image network's size."""

    obs_type: str = "state"  # state | keypoints | image (see the module docstring)
    obs_shapes: tuple[tuple[str, tuple[int, ...]], ...] = ()  # (data key, shape of one step), filled from the data
    agent_dims: int = 2  # leading entries of `state` holding the agent position (keypoints and image obs)
    crop_size: int = 84  # square crop of the image: random in training, centred at evaluation
    resnet_width: int = 64  # ResNet18 stem width (64 is the standard network; smaller for CPU or tests)
    spatial_keypoints: int = 32  # spatial-softmax maps (each gives an expected x, y)
    image_feature_dim: int = 64  # features per image after the spatial softmax's linear map
    goal: bool = False  # the goal varies per episode: also read it (GOAL_KEYS)
    keypoint_key: str = "keypoint"  # data key the keypoints type reads its object points from
    image_norm: str = "group"  # group (gpc, Diffusion Policy) or batch (LeRobot's current default) in the ResNet
    image_feature_relu: bool = False  # a ReLU after the image features' linear map (LeRobot's encoder has one)
    state_spans: tuple[tuple[int, float, float], ...] = ()  # the task's StateLayout.spans: the state normaliser spans them
    # Widths of an MLP over each step's joined features (); none, as Diffusion Policy's. Where a goal is read beside
    # the state, the U-Net sees the observation only through a linear map per block (FiLM): an MLP can first form
    # what depends on both (where the target is from the object).
    mlp: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        if self.obs_type not in OBS_KEYS:
            raise ValueError(f"obs type {self.obs_type!r}: use one of {', '.join(OBS_KEYS)}")
        if self.image_norm not in NORMS:
            raise ValueError(f"image norm {self.image_norm!r}: use one of {', '.join(NORMS)}")
        for name in ("agent_dims", "crop_size", "resnet_width", "spatial_keypoints", "image_feature_dim"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} {getattr(self, name)}: must be at least 1")
        if any(w < 1 for w in self.mlp):
            raise ValueError(f"mlp widths {self.mlp}: each must be at least 1")

    @property
    def keys(self) -> tuple[str, ...]:
        """Data keys this observation type reads."""
        keys = OBS_KEYS[self.obs_type]
        if self.obs_type == "keypoints":
            keys = (self.keypoint_key,) + keys[1:]
        return keys + (GOAL_KEYS[self.obs_type] if self.goal else ())

    def shape(self, key: str) -> tuple[int, ...]:
        shapes = dict(self.obs_shapes)
        if key not in shapes:
            raise ValueError(f"obs type {self.obs_type!r} needs the shape of data key {key!r}; config has {sorted(shapes)}")
        return tuple(shapes[key])


class VectorPart(nn.Module):
    """A vector key, flattened, optionally only its first ``take`` entries (no parameters)."""

    def __init__(self, key: str, shape: tuple[int, ...], take: int | None = None) -> None:
        super().__init__()
        size = 1
        for s in shape:
            size *= s
        if take is not None and take > size:
            raise ValueError(f"data key {key!r}: cannot take {take} entries from a step of {size}")
        self.key, self.take = key, take
        self.out_dim = size if take is None else take

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        flat = x.flatten(start_dim=2)
        return flat if self.take is None else flat[..., : self.take]


def crop_images(x: torch.Tensor, size: int, random: bool) -> torch.Tensor:
    """``(N, H, W, C)`` -> ``(N, size, size, C)``: an independent random crop per image, or the centre."""
    n, h, w = x.shape[:3]
    if not random:
        top, left = (h - size) // 2, (w - size) // 2
        return x[:, top : top + size, left : left + size]
    tops = torch.randint(0, h - size + 1, (n,), device=x.device)
    lefts = torch.randint(0, w - size + 1, (n,), device=x.device)
    offsets = torch.arange(size, device=x.device)
    rows = (tops[:, None] + offsets)[:, :, None]
    cols = (lefts[:, None] + offsets)[:, None, :]
    return x[torch.arange(n, device=x.device)[:, None, None], rows, cols]


class ImagePart(nn.Module):
    """An image key through crop -> ResNet18 -> spatial softmax -> linear."""

    def __init__(self, key: str, shape: tuple[int, ...], config: EncoderConfig) -> None:
        super().__init__()
        if len(shape) != 3:
            raise ValueError(f"data key {key!r}: images must be (H, W, C) per step, got {shape}")
        h, w, c = shape
        if config.crop_size > min(h, w):
            raise ValueError(f"crop_size {config.crop_size} is larger than the {h}x{w} images of {key!r}")
        self.key, self.crop = key, config.crop_size
        self.net = ResNet18Keypoints(c, config.resnet_width, config.spatial_keypoints, config.image_feature_dim,
                                     config.image_norm, config.image_feature_relu)
        self.out_dim = config.image_feature_dim

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, t = x.shape[:2]
        images = crop_images(x.flatten(0, 1), self.crop, random=self.training)
        return self.net(images.permute(0, 3, 1, 2).contiguous()).reshape(b, t, -1)


class ObsEncoder(nn.Module):
    """``{key: (B, T, ...)}`` normalised observations -> ``(B, T, feature_dim)``."""

    def __init__(self, config: EncoderConfig) -> None:
        super().__init__()
        self.config = config
        agent = config.agent_dims
        parts: list[VectorPart | ImagePart]
        if config.obs_type == "state":
            parts = [VectorPart("state", config.shape("state"))]
        elif config.obs_type == "keypoints":
            key = config.keypoint_key
            parts = [VectorPart(key, config.shape(key)), VectorPart("state", config.shape("state"), agent)]
        else:
            parts = [ImagePart("img", config.shape("img"), config), VectorPart("state", config.shape("state"), agent)]
        if config.goal:
            parts += [VectorPart(key, config.shape(key)) for key in GOAL_KEYS[config.obs_type]]
        self.parts = nn.ModuleList(parts)
        self.feature_dim = sum(p.out_dim for p in parts)
        layers: list[nn.Module] = []
        for width in config.mlp:
            layers += [nn.Linear(self.feature_dim, width), nn.Mish()]
            self.feature_dim = width
        self.mlp = nn.Sequential(*layers[:-1])  # ends linear: the U-Net's FiLM maps begin with a Mish

    @property
    def keys(self) -> tuple[str, ...]:
        return self.config.keys

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        parts = cast(Iterable[VectorPart | ImagePart], self.parts)  # what __init__ put there
        return self.mlp(torch.cat([part(obs[part.key]) for part in parts], dim=-1))


def normalized_obs(normalizer: Any, keys: Iterable[str], obs: Mapping[str, Any], device: Any, reader: str) -> dict[str, torch.Tensor]:
    """Raw observations ``{key: array or tensor}`` -> the ``keys`` an encoder reads, normalised float32 on ``device``;
    a missing key fails naming the ``reader`` (a policy, a value function, ...) and what it reads."""
    keys = tuple(keys)
    out = {}
    for key in keys:
        if key not in obs:
            raise ValueError(f"observation lacks key {key!r} (this {reader} reads {', '.join(keys)})")
        value = obs[key] if torch.is_tensor(obs[key]) else torch.as_tensor(np.asarray(obs[key]))
        out[key] = normalizer.normalize(key, value.to(device, torch.float32))
    return out


class ReadsObservations:
    """Mixin of the frozen configs that hold an ``encoder`` (policy, value function, latent models): what it reads,
    and its step shapes fitted to the stores once (a resumed or borrowed encoder must find the shapes it was built for)."""

    encoder: EncoderConfig

    @property
    def obs_type(self) -> str:
        return self.encoder.obs_type

    @property
    def obs_keys(self) -> tuple[str, ...]:
        return self.encoder.keys

    def with_obs_shapes(self, shapes: Mapping[str, tuple[int, ...]]) -> Any:
        """A copy whose encoder knows the step shape of each observation key it reads."""
        missing = [k for k in self.obs_keys if k not in shapes]
        if missing:
            raise ValueError(f"obs type {self.obs_type!r} needs data key(s) {', '.join(missing)}")
        pairs = tuple((k, tuple(int(s) for s in shapes[k])) for k in self.obs_keys)
        return dataclasses.replace(cast(Any, self), encoder=dataclasses.replace(self.encoder, obs_shapes=pairs))

    def fitted_to(self, data: Mapping[str, np.ndarray], source: str, fixed: bool) -> Any:
        """The shapes of ``data``'s rows filled in; ``fixed`` (a resumed run, a frozen encoder): they must equal the
        ones held (``DataError`` naming ``source`` otherwise)."""
        shapes = {k: tuple(int(s) for s in data[k].shape[1:]) for k in self.obs_keys}
        if not fixed:
            return self.with_obs_shapes(shapes)
        held = {k: tuple(v) for k, v in self.encoder.obs_shapes}
        if held != shapes:
            raise DataError(f"{source}: the encoder was built for observation shapes {held}, the datasets have {shapes}")
        return self
