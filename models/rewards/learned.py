"""The learned image reward: a ResNet18 + MLP that reads the task's objects' poses from one frame.

The network predicts each object's pose ``(x, y[, cos theta, sin theta])`` of a frame (labels: the recorded state's
pose entries, ``config.pose_dims``, object after object; an angle as cos, sin has no wrap-around). ``ImageReward``
turns the predicted pose into ``-registration`` against the goal (``gpc.models.rewards.registration``) and aggregates
it like ``RegistrationReward`` (final step or discounted sum), differentiable w.r.t. the pixels of predicted frames::

    frames (K, T, 3, S, S) in [0, 1] -> resize to input_size -> ResNet18 trunk -> pool
        -> MLP (512-256-128) -> (x_n, y_n, cos, sin) -> pose (x, y, theta) -> -registration -> (K,)

Frames of any size are resized to ``input_size``; training shifts them (the label moves with the picture:
``frame_extent``) and blurs them (predicted frames are blurry); see ``gpc.models.rewards.augment``.

``RewardPredictorModule`` trains it (batch in, loss and logs out) and checkpoints it
(``kind="reward"``, task, obs ``image``, input size), normaliser included. The task's vertices, goal and frame
extent are filled into the config by the caller (``with_task``), so this module knows no task.

A task scored by its own state reward (``Task.state_reward`` other than ``registration``: Triangle Drawing's ink,
Block Stacking's heights) has no poses to register: its predictor reads the whole state vector instead
(``StatePredictor``; ``config.state_reward`` names the reward) and ``gpc.models.rewards.image_state`` scores the
read states with that reward, so frames are ranked by the function states are. Both networks live in
``gpc.models.rewards.readers``; this module holds their config, profiles and training.
"""

from __future__ import annotations

import dataclasses
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
from gpc.models.rewards.augment import random_blur, random_shift
from gpc.models.rewards.readers import IMAGE_KEY, STATE_KEY, PosePredictor, StatePredictor
from gpc.models.rewards.registration import PoseReward, RewardConfig, pose_errors
from gpc.models.training.config import OptimConfig, Profile, RunConfig
from gpc.models.training.config_io import PlainConfig
from gpc.models.training.module import TrainableModule

KIND = "reward"
OBS_TYPE = "image"
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
    pose_dims: tuple[int, ...] = ()  # state entries of every object's x, y[, theta], in order (the labels; from the task)
    pose_sizes: tuple[int, ...] = ()  # entries per object (2 or 3); () is one object, all of pose_dims
    vertices: tuple[tuple[float, float], ...] = ()  # object-frame points of the registration loss, object after object
    vertex_counts: tuple[int, ...] = ()  # points per object; () is one object, all of vertices
    goal: tuple[float, ...] | None = None  # default goal, laid out as pose_dims (None: the task draws one per episode)
    frame_extent: float | None = None  # world units a frame spans (from the task); needed for label-consistent shifts
    state_reward: str = ""  # the task's own state reward (its name): the predictor reads the whole state, not poses
    state_dim: int = 0  # the state entries it reads then (all of them)
    keypoints: bool = True  # a state reader of a top-down frame reads the agent and the task's points on maps (readers)
    agent_dims: tuple[int, ...] = ()  # the agent's (x, y) entries then (the task's agent_xy; filled by with_task)
    point_dims: tuple[int, ...] = ()  # the points' (x, y) entry pairs then (the task's StateLayout.points)
    frame_origin: float = 0.0  # world coordinate at a frame's first pixel edge (from the task), for the keypoint
    relabel: str = ""  # a state reader's labels: the task's StateLayout.relabel (filled by with_task)
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
        if self.pose_dims and (len(set(self.pose_dims)) != len(self.pose_dims) or min(self.pose_dims) < 0
                               or sum(self.sizes) != len(self.pose_dims) or any(n not in (2, 3) for n in self.sizes)):
            raise ValueError(f"pose_dims {self.pose_dims}: need distinct state indices, (x, y) or (x, y, theta) per object "
                             f"(pose_sizes {self.pose_sizes})")
        if any(len(v) != 2 for v in self.vertices):
            raise ValueError("vertices: need (x, y) pairs")
        if self.vertex_counts and (sum(self.vertex_counts) != len(self.vertices) or len(self.vertex_counts) != len(self.sizes)):
            raise ValueError(f"vertex_counts {self.vertex_counts}: need one count per object, adding up to the vertices")
        if self.goal is not None and len(self.goal) != len(self.pose_dims):
            raise ValueError(f"goal {self.goal}: need one value per pose entry {self.pose_dims}")
        if self.frame_extent is not None and self.frame_extent <= 0:
            raise ValueError(f"frame_extent {self.frame_extent}: must be positive")
        if self.state_reward and (self.state_dim < 1 or self.pose_dims or self.shift_px > 0):
            raise ValueError(f"state_reward {self.state_reward!r}: a state reader needs state_dim >= 1, no pose_dims and "
                             "shift_px 0 (a shifted frame changes state entries in task-specific ways)")
        if self.relabel and not self.state_reward:
            raise ValueError(f"relabel {self.relabel!r}: only a state reader relabels what it reads")
        agent = self.agent_dims
        if agent and (not self.state_reward or self.frame_extent is None or len(agent) != 2 or len(set(agent)) != 2
                      or min(agent) < 0 or max(agent) >= self.state_dim):
            raise ValueError(f"agent_dims {agent}: a state reader's agent is two distinct state entries (x, y) "
                             "on a frame of known extent")
        points = self.point_dims
        if points and (not self.state_reward or self.frame_extent is None or len(points) % 2 or len(set(points)) != len(points)
                       or min(points) < 0 or max(points) >= self.state_dim or set(points) & set(agent)):
            raise ValueError(f"point_dims {points}: a state reader's points are (x, y) pairs of distinct state entries, not "
                             "the agent's, on a frame of known extent")
        if self.shift_px < 0 or self.blur_sigma < 0 or not 0.0 <= self.blur_prob <= 1.0:
            raise ValueError("shift_px and blur_sigma must be >= 0 and blur_prob in [0, 1]")

    @property
    def sizes(self) -> tuple[int, ...]:
        """Pose entries per object."""
        return self.pose_sizes or ((len(self.pose_dims),) if self.pose_dims else ())

    @property
    def object_vertices(self) -> list[tuple[tuple[float, float], ...]]:
        """Each object's outline points."""
        counts, out, start = self.vertex_counts or (len(self.vertices),), [], 0
        for n in counts:
            out.append(self.vertices[start:start + n])
            start += n
        return out

    def with_task(self, layout: TaskLayout, state_reward: str = "registration") -> RewardPredictorConfig:
        """A copy that knows the task: its name, the objects' pose entries, outlines and default goal, the frame's span;
        for a task scored by its own ``state_reward``, the state it reads instead (no shifts: see ``state_reward``)."""
        if layout.frame is None:
            raise ValueError(f"the learned image reward reads frames; task {layout.name} renders none")
        if state_reward != "registration":
            # a frame that names the agent's colours is top-down over its extent (a camera's is not)
            top_down = self.keypoints and bool(layout.frame.agent_colours)
            agent, points = (layout.state.agent_xy, layout.state.points) if top_down else ((), ())
            return dataclasses.replace(self, task=layout.name, state_reward=state_reward, state_dim=layout.state.dim,
                                       frame_extent=layout.frame.span, frame_origin=layout.frame.extent[0], shift_px=0.0,
                                       agent_dims=agent, point_dims=points, relabel=layout.state.relabel)
        several = len(layout.objects) > 1  # one object keeps the fields a single-object config always had
        return dataclasses.replace(
            self, task=layout.name, pose_dims=layout.pose_dims, goal=layout.goal, frame_extent=layout.frame.span,
            pose_sizes=tuple(len(o.pose) for o in layout.objects) if several else (),
            vertices=tuple(v for o in layout.objects for v in o.vertices),
            vertex_counts=tuple(len(o.vertices) for o in layout.objects) if several else ())

    def check_task(self) -> None:
        if self.state_reward:
            return  # __post_init__ checked the state reader's fields
        if not self.vertices or not self.pose_dims:
            raise ValueError("the reward predictor's config has no pose entries or vertices; fill them with "
                             "config.with_task(layout)")
        if self.shift_px > 0 and self.frame_extent is None:
            raise ValueError("shift augmentation needs frame_extent (the world units a frame spans); see with_task")


def reward_profile(name: str, layout: TaskLayout, input_size: int | None = None, lr: float | None = None,
                   state_reward: str = "registration") -> Profile[RewardPredictorConfig]:
    """``cpu``: ResNet18 at width 32 on 64 px frames; ``paper``: full ResNet18 on 96 px; ``tiny``: tests.
    ``input_size``: the frame size the network reads (match the world model's); ``lr``: another peak learning rate;
    ``state_reward``: the task's (``Task.state_reward``; see ``with_task``)."""
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
    return Profile(config.with_task(layout, state_reward), batch, steps)


class ImageReward(PoseReward):
    """``-registration`` of the pose a predictor reads from each predicted frame (see ``PoseReward``).

    Futures are frames ``(K, T, 3, S, S)`` in [0, 1] at any size ``S`` (resized to
    ``input_size``); ``goal``: ``(P,)`` (default: the predictor's; None where the task draws a goal per
    episode) or, per call, ``(P,)`` or ``(K, P)``. Scores are ``(K,)`` and differentiable w.r.t. the frames.
    """

    def __init__(self, predictor: PosePredictor, goal: Any = None, config: RewardConfig = RewardConfig()) -> None:
        pc = predictor.config
        goal = pc.goal if goal is None else goal
        if not pc.vertices:
            raise ValueError("the image reward needs the predictor's vertices (config.with_task)")
        super().__init__([torch.tensor(v) for v in pc.object_vertices],
                         None if goal is None else torch.as_tensor(goal, dtype=torch.float32), config, pc.sizes)
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
        return self.predictor(frames.flatten(0, 1)).reshape(k, t, -1)


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
        self.predictor = (StatePredictor if config.state_reward else PosePredictor)(config, normalizer)
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
        if config.state_reward and (state.ndim != 2 or state.shape[1] != config.state_dim):
            raise DataError(f"{source}: data/{STATE_KEY} rows are {state.shape[1:]}, the reward reads ({config.state_dim},) states")
        if not config.state_reward and (state.ndim != 2 or state.shape[1] <= max(config.pose_dims)):
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
            states[:, self.predictor.xy_dims] += (shift * (c.frame_extent / c.input_size)).repeat(1, len(c.sizes))  # every object moves
        if c.blur_prob > 0 and c.blur_sigma > 0:
            x = random_blur(x, c.blur_prob, c.blur_sigma)
        return x, states

    def check_ready(self) -> None:
        self.predictor.check_normalizer()
        self.config.check_task()

    def loss(self, batch: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        frames, states = self._frames_states(batch)
        x, states = self._augment(self.predictor.prepare(frames), states)
        loss, parts = self.predictor.fit_loss(x, states)
        return loss, {"loss": loss.detach(), **parts}

    def validation_loss(self, batch: Mapping[str, torch.Tensor], batch_idx: int) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The label loss on unaugmented frames, with the pose and registration-loss errors in px and degrees."""
        frames, states = self._frames_states(batch)
        out = self.predictor.raw(self.predictor.prepare(frames))
        read = self.predictor.to_pose(out)
        states = self.predictor.label(states, read)
        loss = F.mse_loss(out, self.predictor.targets(states))
        c = self.config
        if c.state_reward:  # a state reader: its entries' mean error in raw units (the reward's error: `gpc eval reward`)
            logs = {}
            if c.agent_dims:  # and how far off it places the agent and the points
                logs["agent_err"] = (read - states)[:, list(c.agent_dims)].norm(dim=-1).mean()
            if c.point_dims:
                logs["points_err"] = (read - states)[:, list(c.point_dims)].reshape(len(read), -1, 2).norm(dim=-1).mean()
            return loss, {"state_abs_err": (read - states).abs().mean(), **logs}
        verts = [torch.tensor(v, device=out.device) for v in c.object_vertices]
        goal = None if c.goal is None else torch.tensor(c.goal, device=out.device)
        errors = pose_errors(read, states[:, list(c.pose_dims)], verts, goal, c.sizes)
        names = ("registration_abs_err_px", "vertex_px", "position_px", "angle_deg")
        return loss, {name: errors[name].mean() for name in names if name in errors and not errors[name].isnan().all()}
