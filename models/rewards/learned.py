"""The learned image reward: a ResNet18 + MLP that reads an object's pose from one frame.

The network predicts the object pose ``(x, y, cos theta, sin theta)`` of a frame (labels:
the recorded state's pose, ``config.pose_dims``; the angle as cos, sin has no wrap-around).
``ImageReward`` turns the predicted pose into ``-registration`` against the goal with
``gpc.models.rewards.registration``'s ``registration_distance`` and aggregates it like ``RegistrationReward``
(``RewardConfig``: final step or discounted sum), so it is differentiable w.r.t. the pixels
of predicted frames::

    frames (K, T, 3, S, S) in [0, 1] -> resize to input_size -> ResNet18 trunk -> pool
        -> MLP (512-256-128) -> (x_n, y_n, cos, sin) -> pose (x, y, theta) -> -registration -> (K,)

Frames of any size are resized (differentiably, ``F.interpolate``) to ``input_size``, the
size the network was trained at. Training augments frames with small random translations
(the label moves with the picture, which needs ``frame_extent``: the world units a frame
spans, x along columns, y along rows) and random Gaussian blur (predicted frames are blurry).

``RewardPredictorModule`` trains it (batch in, loss and logs out) and checkpoints it
(``kind="reward"``, task, obs ``image``, input size); ``load_from_checkpoint(path)`` alone
rebuilds it, normaliser included. The task's vertices, goal and frame extent are filled
into the config by the caller (``with_task``), so this module knows no task.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from gpc.datasets.datamodule import DataConfig
from gpc.datasets.errors import DataError
from gpc.datasets.layout import TaskLayout
from gpc.datasets.normalizer import MinMaxNormalizer
from gpc.datasets.windows import EpisodeArrays
from gpc.models.networks.resnet import ResNet18Trunk
from gpc.models.rewards.registration import PoseReward, RewardConfig, registration_distance
from gpc.models.training.config import OptimConfig, Profile, RunConfig
from gpc.models.training.config_io import PlainConfig
from gpc.models.training.module import TrainableModule

KIND = "reward"
OBS_TYPE = "image"
IMAGE_KEY, STATE_KEY = "img", "state"
PROFILES = ("cpu", "paper", "tiny")
POOLS = ("flatten", "avg")


@dataclass(frozen=True)
class RewardPredictorConfig(PlainConfig):
    """The pose predictor behind the image reward: its network, its labels, its augmentation."""

    task: str = ""  # task the predictor is trained for (required); checked when a checkpoint is loaded
    input_size: int = 64  # frames are resized to input_size x input_size px before the network (the size trained at)
    resnet_width: int = 32  # ResNet18 stem width (64 is the standard network)
    pool: str = "flatten"  # flatten: the whole final feature map (keeps where things are); avg: global average
    mlp_dims: tuple[int, ...] = (512, 256, 128)  # hidden layers of the head (ReLU) before the 4 pose outputs
    pose_dims: tuple[int, ...] = ()  # state entries of the object's x, y, theta (the labels; from the task)
    vertices: tuple[tuple[float, float], ...] = ()  # object-frame points of the registration loss (from the task)
    goal: tuple[float, float, float] | None = None  # default goal pose (from the task)
    frame_extent: float | None = None  # world units a frame spans (from the task); needed for label-consistent shifts
    shift_px: float = 4.0  # training: uniform random translation up to this many input pixels (0: none)
    blur_prob: float = 0.5  # training: share of frames blurred
    blur_sigma: float = 1.0  # training: blur standard deviation drawn from U(0, blur_sigma) input pixels
    optim: OptimConfig = field(default_factory=lambda: OptimConfig(lr=1e-3, betas=(0.9, 0.999), warmup_steps=200))

    def __post_init__(self) -> None:
        if not self.task:
            raise ValueError("task must be named")
        if self.input_size < 8 or self.resnet_width < 1:
            raise ValueError(f"input_size {self.input_size} must be >= 8 and resnet_width {self.resnet_width} >= 1")
        if self.pool not in POOLS:
            raise ValueError(f"pool {self.pool!r}: use one of {', '.join(POOLS)}")
        if any(d < 1 for d in self.mlp_dims):
            raise ValueError(f"mlp_dims {self.mlp_dims}: every hidden layer needs at least 1 unit")
        if self.pose_dims and (len(self.pose_dims) != 3 or len(set(self.pose_dims)) != 3 or min(self.pose_dims) < 0):
            raise ValueError(f"pose_dims {self.pose_dims}: need three distinct state indices (x, y, theta)")
        if any(len(v) != 2 for v in self.vertices):
            raise ValueError("vertices: need (x, y) pairs")
        if self.goal is not None and len(self.goal) != 3:
            raise ValueError(f"goal {self.goal}: need (x, y, theta)")
        if self.frame_extent is not None and self.frame_extent <= 0:
            raise ValueError(f"frame_extent {self.frame_extent}: must be positive")
        if self.shift_px < 0 or self.blur_sigma < 0 or not 0.0 <= self.blur_prob <= 1.0:
            raise ValueError("shift_px and blur_sigma must be >= 0 and blur_prob in [0, 1]")

    def with_task(self, layout: TaskLayout) -> RewardPredictorConfig:
        """A copy that knows the task: its name, the object's pose entries, outline and default goal, the frame's span."""
        obj = layout.primary
        if len(layout.objects) != 1 or not obj.has_angle or layout.frame is None:
            raise ValueError(f"the learned image reward reads one object's (x, y, angle) pose from frames; task {layout.name} "
                             "has several objects, no angle in its goal or renders no frames")
        return dataclasses.replace(self, task=layout.name, pose_dims=obj.pose, vertices=obj.vertices,
                                   goal=obj.goal, frame_extent=layout.frame.span)  # type: ignore[arg-type]

    def check_task(self) -> None:
        if not self.vertices or self.goal is None or not self.pose_dims:
            raise ValueError("the reward predictor's config has no pose entries, vertices or goal; fill them with "
                             "config.with_task(layout)")
        if self.shift_px > 0 and self.frame_extent is None:
            raise ValueError("shift augmentation needs frame_extent (the world units a frame spans); see with_task")


def reward_profile(name: str, layout: TaskLayout, input_size: int | None = None,
                   lr: float | None = None) -> Profile[RewardPredictorConfig]:
    """``cpu``: ResNet18 at width 32 on 64 px frames; ``paper``: full ResNet18 on 96 px; ``tiny``: tests.
    ``input_size``: the frame size the network reads (match the world model's); ``lr``: another peak learning rate."""
    task = layout.name
    if name == "cpu":
        # 3.5M parameters; 3,000 steps took 14 min on one thread here (expert + exploration stores),
        # held-out registration-loss error 2.2 px (human data, never seen: 2.0 px).
        config, batch, steps = RewardPredictorConfig(task=task, input_size=64, resnet_width=32), 64, 3000
    elif name == "paper":  # 13.7M parameters; settings not yet run (meant for a GPU)
        optim = OptimConfig(lr=3e-4, betas=(0.9, 0.999), warmup_steps=500)
        config, batch, steps = RewardPredictorConfig(task=task, input_size=96, resnet_width=64, optim=optim), 128, 30000
    elif name == "tiny":
        optim = OptimConfig(lr=3e-3, betas=(0.9, 0.999), warmup_steps=2)
        config = RewardPredictorConfig(task=task, input_size=32, resnet_width=8, mlp_dims=(32, 16), shift_px=2.0, optim=optim)
        batch, steps = 16, 20
    else:
        raise ValueError(f"profile {name!r}: use one of {', '.join(PROFILES)}")
    if input_size is not None:
        config = dataclasses.replace(config, input_size=input_size)
    if lr is not None:
        config = dataclasses.replace(config, optim=dataclasses.replace(config.optim, lr=lr))
    return Profile(config.with_task(layout), batch, steps)


def resize(frames: torch.Tensor, size: int) -> torch.Tensor:
    """``(N, C, H, W)`` -> ``(N, C, size, size)``, antialiased bilinear (differentiable); unchanged if already that size."""
    if frames.shape[-2:] == (size, size):
        return frames
    return F.interpolate(frames, size=(size, size), mode="bilinear", align_corners=False, antialias=True)


def random_shift(x: torch.Tensor, max_px: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Translate each ``(N, C, S, S)`` image by up to ``max_px`` px (edges repeated) -> images, ``(N, 2)`` shifts (x, y) px."""
    n, s = x.shape[0], x.shape[-1]
    shift = (torch.rand(n, 2, device=x.device) * 2.0 - 1.0) * max_px
    theta = torch.zeros(n, 2, 3, device=x.device, dtype=x.dtype)
    theta[:, 0, 0] = theta[:, 1, 1] = 1.0
    theta[:, :, 2] = -2.0 * shift.to(x.dtype) / s  # output(p) = input(p - shift): the content moves by +shift
    grid = F.affine_grid(theta, list(x.shape), align_corners=False)
    return F.grid_sample(x, grid, mode="bilinear", padding_mode="border", align_corners=False), shift


def random_blur(x: torch.Tensor, prob: float, max_sigma: float) -> torch.Tensor:
    """Blur a random ``prob`` share of ``(N, C, H, W)`` images with a Gaussian of sigma ~ U(0, max_sigma) px."""
    n, c, h, w = x.shape
    radius = max(1, math.ceil(2.0 * max_sigma))
    sigma = torch.rand(n, device=x.device) * max_sigma * (torch.rand(n, device=x.device) < prob)
    taps = torch.arange(-radius, radius + 1, device=x.device, dtype=x.dtype)
    kernel = torch.exp(-taps.pow(2) / (2.0 * sigma.clamp_min(1e-3).to(x.dtype)[:, None] ** 2))
    kernel = (kernel / kernel.sum(dim=1, keepdim=True)).repeat_interleave(c, dim=0)  # (N * C, K)
    flat = F.pad(x.reshape(1, n * c, h, w), (radius,) * 4, mode="replicate")
    flat = F.conv2d(flat, kernel[:, None, None, :], groups=n * c)
    flat = F.conv2d(flat, kernel[:, None, :, None], groups=n * c)
    return flat.reshape(n, c, h, w)


class PosePredictor(nn.Module):
    """Normaliser + ResNet18 + MLP: ``(N, 3, H, W)`` frames in [0, 1] -> ``(N, 3)`` poses ``(x, y, theta)``.

    The normaliser holds the fixed ``img`` range (0..255) and the ``state`` range of the
    training data (the label's x, y are predicted in [-1, 1] of that range).
    """

    def __init__(self, config: RewardPredictorConfig, normalizer: MinMaxNormalizer | None = None) -> None:
        super().__init__()
        self.config = config
        self.normalizer = normalizer if normalizer is not None else MinMaxNormalizer()
        self.trunk = ResNet18Trunk(3, config.resnet_width)
        cells = config.input_size
        for _ in range(5):  # stem conv, max-pool and three strided stages each halve the size, rounding up
            cells = -(-cells // 2)
        dims = (self.trunk.out_channels * (cells * cells if config.pool == "flatten" else 1),) + config.mlp_dims
        layers: list[nn.Module] = []
        for a, b in zip(dims[:-1], dims[1:]):
            layers += [nn.Linear(a, b), nn.ReLU()]
        self.head = nn.Sequential(*layers, nn.Linear(dims[-1], 4))
        self._xy = list(config.pose_dims[:2])

    def check_normalizer(self) -> None:
        missing = [k for k in (IMAGE_KEY, STATE_KEY) if k not in self.normalizer.keys()]
        if missing:
            raise ValueError(f"the reward predictor's normaliser has no statistics for {', '.join(missing)}")

    def prepare(self, frames: torch.Tensor) -> torch.Tensor:
        """``(N, 3, H, W)`` in [0, 1] -> ``(N, 3, S, S)`` resized to ``input_size`` and normalised."""
        if frames.dim() != 4 or frames.shape[1] != 3:
            raise ValueError(f"frames: expected (N, 3, H, W), got {tuple(frames.shape)}")
        x = resize(frames, self.config.input_size)
        scale, offset = self.normalizer.scales[IMAGE_KEY], self.normalizer.offsets[IMAGE_KEY]
        return x * (255.0 * scale.to(x.dtype))[:, None, None] + offset.to(x.dtype)[:, None, None]

    def raw(self, x: torch.Tensor) -> torch.Tensor:
        """Prepared ``(N, 3, S, S)`` -> ``(N, 4)`` network outputs ``(x_n, y_n, cos, sin)``."""
        features = self.trunk(x)
        features = features.flatten(1) if self.config.pool == "flatten" else features.mean(dim=(2, 3))
        return self.head(features)

    def targets(self, states: torch.Tensor) -> torch.Tensor:
        """``(N, D)`` raw states -> ``(N, 4)`` labels ``(x_n, y_n, cos theta, sin theta)``."""
        xy = states[:, self._xy] * self.normalizer.scales[STATE_KEY][self._xy] + self.normalizer.offsets[STATE_KEY][self._xy]
        theta = states[:, self.config.pose_dims[2]]
        return torch.cat([xy, torch.cos(theta)[:, None], torch.sin(theta)[:, None]], dim=1)

    def to_pose(self, out: torch.Tensor) -> torch.Tensor:
        """``(N, 4)`` outputs -> ``(N, 3)`` poses ``(x, y, theta)`` in raw units (theta in (-pi, pi])."""
        xy = (out[:, :2] - self.normalizer.offsets[STATE_KEY][self._xy]) / self.normalizer.scales[STATE_KEY][self._xy]
        return torch.cat([xy, torch.atan2(out[:, 3], out[:, 2])[:, None]], dim=1)

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        """``(N, 3, H, W)`` frames in [0, 1] (any size) -> ``(N, 3)`` predicted poses, differentiable."""
        return self.to_pose(self.raw(self.prepare(frames)))


def pose_errors(pred: torch.Tensor, true: torch.Tensor, vertices: torch.Tensor, goal: torch.Tensor) -> dict[str, torch.Tensor]:
    """``(N, 3)`` predicted and true poses -> per-frame errors ``(N,)``: position px, angle deg, vertex px
    (mean vertex distance between the two poses), and the registration loss against ``goal`` (true,
    predicted, absolute error px)."""
    true_reg, pred_reg = registration_distance(true, goal, vertices), registration_distance(pred, goal, vertices)
    turn = torch.remainder(pred[:, 2] - true[:, 2] + math.pi, 2 * math.pi) - math.pi
    return {"position_px": (pred[:, :2] - true[:, :2]).norm(dim=1), "angle_deg": turn.abs() * (180.0 / math.pi),
            "vertex_px": registration_distance(pred, true, vertices), "registration_true_px": true_reg,
            "registration_pred_px": pred_reg, "registration_abs_err_px": (pred_reg - true_reg).abs()}


class ImageReward(PoseReward):
    """``-registration`` of the pose a predictor reads from each predicted frame (see ``PoseReward``).

    Futures are frames ``(K, T, 3, S, S)`` in [0, 1] at any size ``S`` (resized to
    ``input_size``); ``goal``: ``(3,)`` (default: the predictor's) or, per call, ``(3,)`` or
    ``(K, 3)``. Scores are ``(K,)`` and differentiable w.r.t. the frames.
    """

    def __init__(self, predictor: PosePredictor, goal: Any = None, config: RewardConfig = RewardConfig()) -> None:
        pc = predictor.config
        goal = pc.goal if goal is None else goal
        if goal is None or not pc.vertices:
            raise ValueError("the image reward needs the predictor's vertices and a goal (config.with_task)")
        super().__init__(torch.tensor(pc.vertices), torch.as_tensor(goal, dtype=torch.float32), config)
        self.predictor = predictor

    @classmethod
    def from_checkpoint(cls, path: str | os.PathLike, goal: Any = None, config: RewardConfig = RewardConfig(),
                        map_location: Any = "cpu", task: str | None = None) -> ImageReward:
        """The frozen (no parameter gradients) reward of a ``gpc train reward`` checkpoint."""
        predictor = RewardPredictorModule.load_from_checkpoint(path, map_location=map_location, task=task).predictor
        return cls(predictor.requires_grad_(False).eval(), goal, config)

    @property
    def input_size(self) -> int:
        """The frame size the predictor was trained at (other sizes are resized to it)."""
        return self.predictor.config.input_size

    def poses(self, frames: torch.Tensor) -> torch.Tensor:
        if frames.dim() != 5 or frames.shape[2] != 3:
            raise ValueError(f"frames: expected (K, T, 3, S, S), got {tuple(frames.shape)}")
        k, t = frames.shape[:2]
        return self.predictor(frames.flatten(0, 1)).reshape(k, t, 3)


class RewardPredictorModule(TrainableModule):
    """The image reward's pose predictor for one task: batch in, loss and logs out; ``reward()`` for planners.

    It trains on single-frame windows (``n_obs_steps = horizon = 1``) of every episode, split by
    whole episodes, labelled by the recorded states.
    """

    KIND, WHAT = KIND, "reward"

    def __init__(self, config: RewardPredictorConfig | Mapping[str, Any], normalizer: MinMaxNormalizer | None = None,
                 data: Mapping[str, Any] | None = None) -> None:
        config = RewardPredictorConfig.from_dict(config)
        super().__init__(config, data)
        self.config: RewardPredictorConfig = config
        self.predictor = PosePredictor(config, normalizer)
        self.track_ema()

    @property
    def input_size(self) -> int:
        return self.config.input_size

    def reward(self, goal: Any = None, config: RewardConfig = RewardConfig()) -> ImageReward:
        """The reward over this module's predictor (shared weights)."""
        return ImageReward(self.predictor, goal, config)

    # ------------------------------------------------------------------ the training contract
    @property
    def network(self) -> nn.Module:
        return self.predictor

    def record(self) -> dict[str, Any]:
        return {"obs": OBS_TYPE, "input_size": self.config.input_size}

    @classmethod
    def expected_record(cls, obs_type: str | None) -> dict[str, Any]:
        return {"obs": OBS_TYPE}

    @classmethod
    def config_from_dict(cls, data: Any) -> RewardPredictorConfig:
        return RewardPredictorConfig.from_dict(data)

    @classmethod
    def check_resume(cls, stored: RewardPredictorConfig, given: RewardPredictorConfig, path: str) -> None:
        """Any stored predictor config may be resumed (they all read images)."""

    @classmethod
    def data_config(cls, config: RewardPredictorConfig, datasets: tuple[str, ...], run: RunConfig,
                    split: tuple[int, float]) -> DataConfig:
        """Single-frame windows: one image and its recorded state per sample."""
        return DataConfig(paths=datasets, obs_keys=(IMAGE_KEY, STATE_KEY), horizon=1, n_obs_steps=1, n_action_steps=1,
                          val_ratio=split[1], seed=split[0], batch_size=run.batch_size, num_workers=run.num_workers)

    @classmethod
    def fit_to_data(cls, config: RewardPredictorConfig, arrays: EpisodeArrays, source: str,
                    resumed: bool) -> RewardPredictorConfig:
        config.check_task()
        img, state = arrays.data[IMAGE_KEY], arrays.data[STATE_KEY]
        if img.ndim != 4 or img.shape[-1] != 3:
            raise DataError(f"{source}: data/{IMAGE_KEY} rows are {img.shape[1:]}, the reward needs RGB frames (H, W, 3)")
        if state.ndim != 2 or state.shape[1] <= max(config.pose_dims):
            raise DataError(f"{source}: data/{STATE_KEY} rows are {state.shape[1:]}, the pose sits at {config.pose_dims}")
        return config

    def _frames_states(self, batch: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """Single-frame windows ``img (B, 1, H, W, 3)`` 0..255, ``state (B, 1, D)`` -> ``(B, 3, H, W)`` in [0, 1], ``(B, D)``."""
        frames = batch[IMAGE_KEY][:, -1].float().permute(0, 3, 1, 2) / 255.0
        return frames, batch[STATE_KEY][:, -1].float()

    def _augment(self, x: torch.Tensor, states: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        c = self.config
        if c.shift_px > 0:
            assert c.frame_extent is not None  # check_task
            x, shift = random_shift(x, c.shift_px)
            states = states.clone()
            states[:, list(c.pose_dims[:2])] += shift * (c.frame_extent / c.input_size)
        if c.blur_prob > 0 and c.blur_sigma > 0:
            x = random_blur(x, c.blur_prob, c.blur_sigma)
        return x, states

    def check_ready(self) -> None:
        self.predictor.check_normalizer()
        self.config.check_task()

    def loss(self, batch: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        frames, states = self._frames_states(batch)
        x, states = self._augment(self.predictor.prepare(frames), states)
        loss = F.mse_loss(self.predictor.raw(x), self.predictor.targets(states))
        return loss, {"loss": loss.detach()}

    def validation_loss(self, batch: Mapping[str, torch.Tensor], batch_idx: int) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The label loss on unaugmented frames, with the pose and registration-loss errors in px and degrees."""
        frames, states = self._frames_states(batch)
        out = self.predictor.raw(self.predictor.prepare(frames))
        loss = F.mse_loss(out, self.predictor.targets(states))
        verts = torch.tensor(self.config.vertices, device=out.device)
        goal = torch.tensor(self.config.goal, device=out.device)
        errors = pose_errors(self.predictor.to_pose(out), states[:, list(self.config.pose_dims)], verts, goal)
        names = ("registration_abs_err_px", "vertex_px", "position_px", "angle_deg")
        return loss, {name: errors[name].mean() for name in names}
