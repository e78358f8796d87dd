"""Push-T as LeRobot and Diffusion Policy name it: observation features, and LeRobot datasets both ways.

gym-pusht (LeRobot's Push-T) observes the agent's position (``observation.state``), the T's 8
outline vertices (``observation.environment_state``) and the camera (``observation.image``);
Diffusion Policy's low-dim policies read its 9 keypoints then the agent (``keypoint``,
``agent_pos``). gpc's state adds the block pose, which the vertices determine: a LeRobot
dataset with ``environment_state`` converts to a full gpc store.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from gpc.datasets.errors import DataError
from gpc.tasks.pusht import geometry

FOREIGN_FEATURES: dict[str, tuple[str, int | None]] = {
    "observation.state": ("state", 2),  # the agent's position
    "observation.environment_state": ("vertex", None),  # gym-pusht's 8 outline vertices
    "observation.image": ("img", None),
    "agent_pos": ("state", 2),
    "image": ("img", None),
    "keypoint": ("keypoint", None),  # Diffusion Policy's low-dim obs: these 9 keypoints, then agent_pos
}


def outline_vertices(obs: Mapping[str, np.ndarray]) -> np.ndarray:
    """The ``vertex`` observation (8, 2) of a step (or steps), from its state."""
    return geometry.outline_vertices(np.asarray(obs["state"], dtype=np.float64)[..., 2:5]).astype(np.float32)


def to_lerobot(episode: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """An episode of a gpc store as gym-pusht's features (LeRobot's ``pusht_keypoints``, plus the image if stored)."""
    state = np.asarray(episode["state"], dtype=np.float32)
    out = {"observation.state": state[:, :2].copy(),
           "observation.environment_state": outline_vertices(episode).reshape(len(state), 16),
           "action": np.asarray(episode["action"], dtype=np.float32)}
    if "img" in episode:
        out["observation.image"] = np.asarray(episode["img"], dtype=np.uint8)
    return out


def from_lerobot(features: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """gym-pusht's features -> a gpc episode (state with the block pose fitted to the vertices, keypoints, image)."""
    missing = [k for k in ("observation.state", "observation.environment_state", "action") if k not in features]
    if missing:
        raise DataError(f"Push-T needs {', '.join(missing)} to rebuild its state (the block pose comes from "
                        "observation.environment_state, as in lerobot/pusht_keypoints)")
    agent = np.asarray(features["observation.state"], dtype=np.float64).reshape(-1, 2)
    pose = geometry.pose_from_outline(np.asarray(features["observation.environment_state"], dtype=np.float64).reshape(-1, 8, 2))
    out = {"state": np.concatenate([agent, pose], axis=1).astype(np.float32),
           "keypoint": geometry.block_keypoints(pose).astype(np.float32),
           "action": np.asarray(features["action"], dtype=np.float32).reshape(-1, 2)}
    if "observation.image" in features:
        out["img"] = np.asarray(features["observation.image"], dtype=np.uint8)
    return out
