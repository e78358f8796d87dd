"""The networks that read a frame: each object's pose (``PosePredictor``) or a whole state (``StatePredictor``).

Both are a normaliser, a ResNet18 trunk and an MLP head (``gpc.models.rewards.learned`` trains them). A state
reader of a top-down frame reads the agent's position by a soft-argmax over a map of the trunk's first stage
(stride 4, ``config.agent_dims``) instead: the agent is a small marker (the drawing's pen, a ring 26 px wide on a
512 px canvas) which the trunk's last map (2 x 2 cells at 64 px) keeps only as a code the head must decode scene by
scene (the head alone read the pen 108 px off on held-out drawings). The map is trained to peak where the agent is
(a heatmap target, as keypoint detectors are), and the frame's extent turns its expected cell into world units.
"""

from __future__ import annotations

import itertools
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import nn

from gpc.datasets.normalizer import MinMaxNormalizer
from gpc.models.named import load_named
from gpc.models.networks.resnet import ResNet18Trunk
from gpc.models.rewards.augment import resize

if TYPE_CHECKING:
    from gpc.models.rewards.learned import RewardPredictorConfig

IMAGE_KEY, STATE_KEY = "img", "state"
MAP_WEIGHT = 0.1  # each keypoint map's cross-entropy (about 5.5 untrained at 16 x 16 cells) beside the label loss
OFFSET_WEIGHT = 10.0  # the points' offset error (squared, in cells: 0.17 untrained), then MAP_WEIGHT as the maps': 1 in all



class PosePredictor(nn.Module):
    """Normaliser + ResNet18 + MLP: ``(N, 3, H, W)`` frames in [0, 1] -> ``(N, P)`` poses, each object's ``(x, y[, theta])``.

    The normaliser holds the fixed ``img`` range (0..255) and the ``state`` range of the
    training data (the labels' x, y are predicted in [-1, 1] of that range).
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
        self.sizes = config.sizes
        self.head = nn.Sequential(*layers, nn.Linear(dims[-1], self.outputs()))
        starts = [sum(self.sizes[:i]) for i in range(len(self.sizes))]
        self.xy_dims = [config.pose_dims[s + j] for s in starts for j in (0, 1)]  # every object's x, y entries
        self._angles = [config.pose_dims[s + 2] for s, n in zip(starts, self.sizes) if n == 3]

    def outputs(self) -> int:
        """The head's outputs: each object's ``(x_n, y_n[, cos, sin])``."""
        return sum(2 + 2 * (n == 3) for n in self.config.sizes)

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
        """Prepared ``(N, 3, S, S)`` -> ``(N, O)`` network outputs, each object's ``(x_n, y_n[, cos, sin])``."""
        return self.head(self.pool(self.trunk(x)))

    def pool(self, features: torch.Tensor) -> torch.Tensor:
        """The trunk's last map -> the head's input."""
        return features.flatten(1) if self.config.pool == "flatten" else features.mean(dim=(2, 3))

    def targets(self, states: torch.Tensor) -> torch.Tensor:
        """``(N, D)`` raw states -> ``(N, O)`` labels, each object's ``(x_n, y_n[, cos theta, sin theta])``."""
        xy = states[:, self.xy_dims] * self.normalizer.scales[STATE_KEY][self.xy_dims] + self.normalizer.offsets[STATE_KEY][self.xy_dims]
        parts, turns = [], iter(self._angles)
        for i, n in enumerate(self.sizes):
            parts.append(xy[:, 2 * i : 2 * i + 2])
            if n == 3:
                theta = states[:, next(turns)]
                parts += [torch.cos(theta)[:, None], torch.sin(theta)[:, None]]
        return torch.cat(parts, dim=1)

    def to_pose(self, out: torch.Tensor) -> torch.Tensor:
        """``(N, O)`` outputs -> ``(N, P)`` poses, each object's ``(x, y[, theta])`` in raw units (theta in (-pi, pi])."""
        parts, col = [], 0
        for i, n in enumerate(self.sizes):
            xy_dims = self.xy_dims[2 * i : 2 * i + 2]
            parts.append((out[:, col : col + 2] - self.normalizer.offsets[STATE_KEY][xy_dims]) / self.normalizer.scales[STATE_KEY][xy_dims])
            if n == 3:
                parts.append(torch.atan2(out[:, col + 3], out[:, col + 2])[:, None])
            col += 2 + 2 * (n == 3)
        return torch.cat(parts, dim=1)

    def label(self, states: torch.Tensor, read: torch.Tensor | None = None) -> torch.Tensor:
        """``(N, D)`` recorded states -> the states this reader is trained to read (here: themselves)."""
        return states

    def fit_loss(self, x: torch.Tensor, states: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Training loss on prepared frames and their recorded states, with any terms worth logging."""
        return F.mse_loss(self.raw(x), self.targets(states)), {}

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        """``(N, 3, H, W)`` frames in [0, 1] (any size) -> ``(N, P)`` predicted poses, differentiable."""
        return self.to_pose(self.raw(self.prepare(frames)))


class StatePredictor(PosePredictor):
    """``(N, 3, H, W)`` frames -> ``(N, D)`` whole states, each entry predicted in [-1, 1] of its training range: the
    reader of a task scored by its own state reward (``config.state_reward``). Where given, the agent's entries
    (``config.agent_dims``) are read on a keypoint map, and the points' (``config.point_dims``: a drawing's corners)
    are a second map's highest peaks, each moved by an offset regressed within its cell (a cell is 32 px of a 512 px
    canvas at 64 px; on held-out drawings the offset at a corner's own cell places it 7 px from the truth) and put in
    the order of the head's readings of them."""

    agent_index: torch.Tensor
    point_index: torch.Tensor
    orders: torch.Tensor

    def __init__(self, config: RewardPredictorConfig, normalizer: MinMaxNormalizer | None = None) -> None:
        super().__init__(config, normalizer)
        self.register_buffer("agent_index", torch.tensor(config.agent_dims, dtype=torch.long), persistent=False)
        self.register_buffer("point_index", torch.tensor(config.point_dims, dtype=torch.long), persistent=False)
        maps = bool(config.agent_dims) + 3 * bool(config.point_dims)  # the points': a heat map and an (x, y) offset
        if maps:
            self.locate = nn.Conv2d(config.resnet_width, maps, 1)  # the first stage keeps the stem's width
        points = len(config.point_dims) // 2  # their assignments to the head's readings, every order (a few points)
        self.register_buffer("orders", torch.tensor(list(itertools.permutations(range(points))), dtype=torch.long),
                             persistent=False)
        self.relabel = load_named(config.relabel, "relabel") if config.relabel else None

    def label(self, states: torch.Tensor, read: torch.Tensor | None = None) -> torch.Tensor:
        """The task's labelling of what a frame shows (``StateLayout.relabel``; its reward is the same on each): of
        several a picture cannot tell apart, the one nearest the states ``read`` from it (``(N, D)``), else the first."""
        if self.relabel is None:
            return states
        options = self.relabel(states)
        if options.dim() == 2:
            return options
        if read is None:
            return options[:, 0]
        gap = (self.targets(options) - self.targets(read)[:, None]).square().sum(-1)
        return options[torch.arange(len(states), device=states.device), gap.argmin(dim=1)]

    def outputs(self) -> int:
        return self.config.state_dim

    def raw(self, x: torch.Tensor) -> torch.Tensor:
        return self.read(x)[0]

    def read(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
        """Prepared frames -> ``(N, D)`` outputs, the maps' logits ``(N, maps, h, w)`` (None without; the points' heat
        map and two offset channels last) and the head's own outputs."""
        if not (self.config.agent_dims or self.config.point_dims):
            out = super().raw(x)
            return out, None, out
        early = self.trunk.stages[0](self.trunk.stem(x))
        head = self.head(self.pool(self.trunk.stages[1:](early)))
        logits = self.locate(early)
        grid, out = self._grid(logits), head
        if self.config.agent_dims:
            xy = torch.softmax(logits[:, 0].flatten(1), dim=-1) @ grid
            out = out.index_copy(1, self.agent_index, self._normalised(xy, self.agent_index))
        if self.config.point_dims:
            points = self._points(logits, grid, self.to_pose(head)[:, self.point_index].reshape(len(x), -1, 2))
            out = out.index_copy(1, self.point_index, self._normalised(points.flatten(1), self.point_index))
        return out, logits, head

    def _points(self, logits: torch.Tensor, grid: torch.Tensor, rough: torch.Tensor) -> torch.Tensor:
        """``(N, P, 2)``: the heat map's P highest local peaks, each moved by its cell's offset, assigned to the head's
        rough readings ``rough`` (the order nearest them: the head tells which point is which, the map where)."""
        heat, offset = logits[:, -3], logits[:, -2:]
        cell = self._cell(heat)
        peaks = torch.where(heat == F.max_pool2d(heat[:, None], 3, 1, 1)[:, 0], heat, heat.new_tensor(float("-inf")))
        idx = peaks.flatten(1).topk(rough.shape[1], dim=1).indices  # (N, P) cells
        found = grid[idx] + self._at(offset, idx) * cell
        cost = (found[:, self.orders] - rough[:, None]).square().sum((2, 3))  # (N, orders)
        best = self.orders[cost.argmin(dim=1)]  # (N, P)
        return found.gather(1, best[..., None].expand(-1, -1, 2))

    @staticmethod
    def _at(maps: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """Two-channel maps ``(N, 2, h, w)`` read at flat cells ``idx`` ``(N, P)`` -> ``(N, P, 2)``."""
        return maps.flatten(2).gather(2, idx[:, None].expand(-1, 2, -1)).transpose(1, 2)

    def _cell(self, maps: torch.Tensor) -> float:
        """World units a cell of maps ``(..., h, w)`` spans (square cells over the frame's extent)."""
        return self.config.frame_extent / maps.shape[-1]  # type: ignore[operator]

    def _normalised(self, values: torch.Tensor, dims: torch.Tensor) -> torch.Tensor:
        return values * self.normalizer.scales[STATE_KEY][dims] + self.normalizer.offsets[STATE_KEY][dims]

    def _grid(self, logits: torch.Tensor) -> torch.Tensor:
        """``(h * w, 2)`` world ``(x, y)`` of each map cell's centre (x along columns, y along rows)."""
        h, w = logits.shape[-2:]
        extent, origin = self.config.frame_extent, self.config.frame_origin
        rows = (torch.arange(h, device=logits.device, dtype=logits.dtype) + 0.5) / h * extent + origin  # type: ignore[operator]
        cols = (torch.arange(w, device=logits.device, dtype=logits.dtype) + 0.5) / w * extent + origin  # type: ignore[operator]
        return torch.cartesian_prod(rows, cols).flip(-1)

    def _blobs(self, logits: torch.Tensor, where: torch.Tensor) -> torch.Tensor:
        """Cross-entropy of maps ``(N, h, w)`` against blobs one cell wide at ``where`` ``(N, P, 2)``, equal shares."""
        cell = self._cell(logits)
        gap = (self._grid(logits) - where[:, :, None]).square().sum(-1) / cell**2  # (N, P, h * w)
        target = torch.softmax(-0.5 * gap, dim=-1).mean(dim=1)
        return -(target * torch.log_softmax(logits.flatten(1), dim=-1)).sum(-1).mean()

    def fit_loss(self, x: torch.Tensor, states: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The label loss, plus a cross-entropy pulling each map onto blobs where its agent or points are (squared error
        alone lets a map settle on any fixed cell, a border's, and answer the mean), and each point's offset from its
        cell's centre; the points' rough reading (the head's) keeps its own label loss. Of labellings a picture cannot
        tell apart, the one nearest the head's is learned."""
        out, logits, head = self.read(x)
        states = self.label(states, self.to_pose(head.detach()))
        targets = self.targets(states)
        loss, parts = F.mse_loss(out, targets), dict[str, torch.Tensor]()
        if logits is None:
            return loss, parts
        n = len(x)
        if self.config.agent_dims:
            parts["agent_ce"] = self._blobs(logits[:, 0], states[:, self.agent_index].reshape(n, 1, 2))
        if self.config.point_dims:
            dims = self.point_index
            loss = loss + F.mse_loss(head[:, dims], targets[:, dims]) * len(dims) / targets.shape[1]
            where = states[:, dims].reshape(n, -1, 2)
            parts["points_ce"] = self._blobs(logits[:, -3], where)
            parts["points_offset"] = self._offset_loss(logits[:, -2:], where)
        return loss + MAP_WEIGHT * sum(parts.values()), {k: v.detach() for k, v in parts.items()}

    def _offset_loss(self, offset: torch.Tensor, where: torch.Tensor) -> torch.Tensor:
        """Squared error, in cells, of the offset maps ``(N, 2, h, w)`` at each point's cell against where in that cell
        the point ``where`` ``(N, P, 2)`` lies, from its centre (x, y), weighted ``OFFSET_WEIGHT``."""
        h, w = offset.shape[-2:]
        at = (where - self.config.frame_origin) / self._cell(offset)  # in cells
        col, row = at[..., 0].floor().clamp(0, w - 1), at[..., 1].floor().clamp(0, h - 1)
        target = (at - torch.stack([col, row], dim=-1) - 0.5).clamp(-0.5, 0.5)
        return OFFSET_WEIGHT * (self._at(offset, (row * w + col).long()) - target).square().sum(-1).mean()

    def targets(self, states: torch.Tensor) -> torch.Tensor:
        return states * self.normalizer.scales[STATE_KEY] + self.normalizer.offsets[STATE_KEY]

    def to_pose(self, out: torch.Tensor) -> torch.Tensor:
        """``(N, D)`` outputs -> ``(N, D)`` states in raw units (an entry that never varied reads as its one value)."""
        return (out - self.normalizer.offsets[STATE_KEY]) / self.normalizer.scales[STATE_KEY]
