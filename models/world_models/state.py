"""The state world model's dynamics: the MLP single-step predictor and its batched, differentiable rollout.

``StateDynamics`` (normaliser + MLP) is the part a planner needs: ``rollout`` maps raw state
histories and raw action chunks to raw predicted states, in one batched call that
gradients flow through. ``gpc.models.world_models.module.WorldModelModule`` wraps it (or
the visual ``VisualDynamics``) for training and checkpoints.

Inputs and outputs of the predictor (``D`` state entries, ``A`` action entries):

- each history state enters as its normalised linear entries plus ``cos``, ``sin`` of its
  angles (no 2 pi discontinuity), with the ``H - 1`` consecutive differences (angles
  wrapped to [-pi, pi)) z-scored by the one-step delta statistics;
- the action enters normalised, and relative to the state entries it targets (Push-T: the
  agent position the PD controller drives towards);
- the network predicts the z-scored delta to the next state; the angle delta is a wrapped
  delta, so ``s_{t+1} = s_t + delta`` and angles are reported modulo 2 pi;
- with an ``object_frame`` (Push-T: the block), the agent's positions, the action and the
  block's earlier positions also enter as offsets in the block's current frame, and the
  block's predicted displacement is read in that frame (the z-scoring is the world frame's:
  its x and y spreads are alike).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import torch
from torch import nn

from gpc.datasets.normalizer import MinMaxNormalizer
from gpc.models.networks.mlp import MLP
from gpc.models.world_models.config import DynamicsConfig, WorldModelConfig

STATE_KEY, ACTION_KEY, DELTA_KEY = "state", "action", "state_delta"
TWO_PI = 2.0 * math.pi


def wrap_angle(x: torch.Tensor) -> torch.Tensor:
    """Angles to [-pi, pi) (gradient 1 almost everywhere)."""
    return torch.remainder(x + math.pi, TWO_PI) - math.pi


def rotate(points: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Planar points ``(..., 2)`` turned by ``angle`` (broadcast over the points' leading dims)."""
    c, s = torch.cos(angle), torch.sin(angle)
    px, py = points[..., 0], points[..., 1]
    return torch.stack([c * px - s * py, s * px + c * py], dim=-1)


def delta_statistics(states: np.ndarray, episode_ends: np.ndarray, episodes: np.ndarray,
                     angle_dims: tuple[int, ...], floor: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """``(mean - std, mean + std)`` of one-step state differences inside the given episodes.

    Angle differences are wrapped to [-pi, pi). ``MinMaxNormalizer.add(DELTA_KEY, lo, hi)``
    with these bounds z-scores a delta. ``std`` is floored at ``floor`` (px, rad) so a
    feature that never moves cannot blow up.
    """
    parts = []
    for i in episodes:
        start = int(episode_ends[i - 1]) if i else 0
        ep = np.asarray(states[start : int(episode_ends[i])], dtype=np.float64)
        if len(ep) > 1:
            parts.append(np.diff(ep, axis=0))
    if not parts:
        raise ValueError("no episode has two steps: cannot fit the world model's delta statistics")
    d = np.concatenate(parts)
    d[:, list(angle_dims)] = np.remainder(d[:, list(angle_dims)] + np.pi, 2 * np.pi) - np.pi
    mean, std = d.mean(axis=0), np.maximum(d.std(axis=0), floor)
    return mean - std, mean + std


class StateDynamics(nn.Module):
    """Normaliser + MLP: the single-step predictor and its recursive rollout, in raw state units.

    The normaliser holds ``state`` and ``action`` (min-max) and ``state_delta`` (z-score)
    statistics of the training data.
    """

    angle_mask: torch.Tensor  # registered (non-persistent) buffers
    object_xy: torch.Tensor

    def __init__(self, config: DynamicsConfig, normalizer: MinMaxNormalizer | None = None) -> None:
        super().__init__()
        self.config = config
        self.normalizer = normalizer if normalizer is not None else MinMaxNormalizer()
        self.net = MLP(config.in_dim, config.state_dim, config.width, config.depth, config.activation, config.layer_norm)
        mask = torch.zeros(config.state_dim, dtype=torch.bool)
        mask[list(config.angle_dims)] = True
        self.register_buffer("angle_mask", mask, persistent=False)
        self._linear = list(config.linear_dims)
        self._angles = list(config.angle_dims)
        self._targets = list(config.action_target_dims)
        self._object = list(config.object_frame)
        self.register_buffer("object_xy", torch.tensor(config.object_frame[:2], dtype=torch.long), persistent=False)

    def check_normalizer(self) -> None:
        missing = [k for k in (STATE_KEY, ACTION_KEY, DELTA_KEY) if k not in self.normalizer.keys()]
        if missing:
            raise ValueError(f"the world model's normaliser has no statistics for {', '.join(missing)}")

    # ------------------------------------------------------------------ one step
    def difference(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """``a - b`` with angle entries wrapped to [-pi, pi)."""
        d = a - b
        return torch.where(self.angle_mask, wrap_angle(d), d)

    def _features(self, history: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """``(K, H, D)`` raw history, ``(K, A)`` raw action -> ``(K, in_dim)``."""
        k, action_n = history.shape[0], self.normalizer.normalize(ACTION_KEY, action)
        parts = [self.normalizer.normalize(STATE_KEY, history)[..., self._linear].reshape(k, -1)]
        if self._angles:
            angles = history[..., self._angles]
            parts += [torch.cos(angles).reshape(k, -1), torch.sin(angles).reshape(k, -1)]
        if history.shape[1] > 1:
            steps = self.difference(history[:, 1:], history[:, :-1])
            parts.append((steps * self.normalizer.scales[DELTA_KEY]).reshape(k, -1))
        parts.append(action_n)
        if self._targets:
            parts.append(action_n - self.normalizer.normalize(ACTION_KEY, history[:, -1, self._targets]))
        if self._object:
            parts.append(self._object_points(history, action))
        return torch.cat(parts, dim=-1)

    def _object_points(self, history: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Where the pusher was, where it is sent and where the object was, seen from the object now.

        Contact dynamics do not change when the whole scene is moved or turned; in the object's
        frame one push looks the same wherever it happens, so the network need not learn it
        once per pose.
        """
        k, (x, y, a) = history.shape[0], self._object
        points = [history[:, :-1, [x, y]]]
        if self._targets:
            points = [history[..., self._targets], action[:, None], *points]
        offsets = torch.cat(points, dim=1) - history[:, -1:, [x, y]]
        return rotate(offsets, -history[:, -1:, a]).reshape(k, -1) / self.config.object_length

    def step(self, history: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """``(K, H, D)`` raw history, ``(K, A)`` raw action -> ``(K, D)`` raw next state (angles unwrapped).

        With an object frame the network's object displacement is read in that frame and turned
        back to the world's.
        """
        delta = self.normalizer.unnormalize(DELTA_KEY, self.net(self._features(history, action)))
        if self._object:
            x, y, a = self._object
            moved = rotate(delta[:, [x, y]], history[:, -1, a])
            delta = delta.index_copy(1, self.object_xy, moved)
        return history[:, -1] + delta

    # ------------------------------------------------------------------ rollout
    def unroll(self, history: torch.Tensor, actions: torch.Tensor, detach_feedback: bool = False) -> torch.Tensor:
        """``(K, H, D)``, ``(K, T, A)`` raw -> ``(K, T, D)`` raw predictions (angles unwrapped)."""
        window = history
        out = []
        for t in range(actions.shape[1]):
            nxt = self.step(window, actions[:, t])
            out.append(nxt)
            fed = nxt.detach() if detach_feedback else nxt
            window = torch.cat([window[:, 1:], fed[:, None]], dim=1)
        return torch.stack(out, dim=1)

    def rollout(self, history: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """``(K, H', D)`` or ``(H', D)`` raw states (the last H are read; one history is broadcast to
        all K), ``(K, T, A)`` raw actions -> ``(K, T, D)`` raw predicted states, angles in [0, 2 pi)."""
        c = self.config
        if actions.dim() != 3 or actions.shape[-1] != c.action_dim:
            raise ValueError(f"actions: expected (K, T, {c.action_dim}), got {tuple(actions.shape)}")
        if history.dim() == 2:
            history = history.unsqueeze(0).expand(actions.shape[0], -1, -1)
        if history.dim() != 3 or history.shape[-1] != c.state_dim or history.shape[1] < c.history:
            raise ValueError(f"history: expected (K, H >= {c.history}, {c.state_dim}) or (H, {c.state_dim}), "
                             f"got {tuple(history.shape)}")
        if history.shape[0] != actions.shape[0]:
            raise ValueError(f"history batch {history.shape[0]} differs from actions batch {actions.shape[0]}")
        history = history[:, -c.history :]
        if not bool(torch.isfinite(history).all()) or not bool(torch.isfinite(actions).all()):
            raise ValueError("history or actions hold NaN or inf")  # a NaN would silently win or lose every ranking
        states = self.unroll(history, actions)
        return torch.where(self.angle_mask, torch.remainder(states, TWO_PI), states)

    @property
    def n_obs_steps(self) -> int:
        return self.config.history

    # ------------------------------------------------------------------ loss
    def window_loss(self, batch: Mapping[str, torch.Tensor], config: WorldModelConfig) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """A training batch ``{state: (B, H + T, D), action: (B, H + T, A)}`` -> loss, logs (see ``loss``)."""
        h, t = self.config.history, config.horizon
        states = batch[STATE_KEY].float()
        actions = batch[ACTION_KEY].float()[:, h - 1 : h - 1 + t]
        return self.loss(states, actions, config.unroll_steps, config.loss_scale, config.detach_feedback)

    # ------------------------------------------------------------------ loss
    def loss(self, states: torch.Tensor, actions: torch.Tensor, unroll: int, units: str = "delta",
             detach_feedback: bool = False) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Windows ``(B, H + T, D)`` raw states, ``(B, T, A)`` raw actions -> mean squared error.

        The T steps are cut into segments of ``unroll`` predictions, each started from the
        true history before it: ``unroll = 1`` is the one-step (teacher-forced) loss,
        ``unroll = T`` the fully unrolled one. Every predicted state is supervised. Errors
        (angles wrapped) are measured in ``units``: ``delta`` divides each entry by its
        one-step delta's standard deviation, ``state`` by half its range in the data.
        """
        h, (b, t) = self.config.history, actions.shape[:2]
        if states.shape[1] != h + t:
            raise ValueError(f"windows hold {states.shape[1]} states for {t} actions; expected H + T = {h + t}")
        starts = range(0, t, unroll)
        history = torch.stack([states[:, j : j + h] for j in starts], dim=1).flatten(0, 1)
        target = torch.stack([states[:, h + j : h + j + unroll] for j in starts], dim=1).flatten(0, 1)
        segments = actions.reshape(b * len(starts), unroll, -1)
        pred = self.unroll(history, segments, detach_feedback)
        err = self.difference(pred, target) * self.normalizer.scales[DELTA_KEY if units == "delta" else STATE_KEY]
        per_step = err.pow(2).mean(dim=(0, 2))
        loss = per_step.mean()
        return loss, {"loss": loss.detach(), "loss_last_step": per_step[-1].detach()}
