"""What the planner tests share: tiny checkpoints trained on real expert episodes, Push-T histories and planners."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gpc.harness.collection import CollectJob, collect
from gpc.harness.evaluation import episode_generator
from gpc.harness.recipes import RewardSpec, build_reward
from gpc.models.planning.config import PlannerConfig
from gpc.models.planning.planner import Planner, model_planner
from gpc.models.policy.config import policy_profile
from gpc.models.policy.module import PolicyModule
from gpc.models.training.config import RunConfig
from gpc.models.training.trainer import train
from gpc.models.world_models.module import WorldModelModule
from gpc.models.world_models.profiles import world_model_profile
from gpc.tasks import get_task
from gpc.tasks.pusht import LAYOUT
from gpc.tasks.pusht.env import PushTEnv
from gpc.tasks.pusht.record import observe

PUSHT = get_task("pusht")


def train_checkpoints(tmp: Path) -> dict[str, str]:
    """A keypoint policy and a state world model, each trained a few steps on real expert episodes."""
    collect(CollectJob(task="pusht", out=tmp / "expert.zarr", episodes=4, images=False, max_steps=60))
    run = dict(batch_size=32, progress=False, accelerator="cpu")
    policy = train(PolicyModule, policy_profile("tiny", "keypoints", LAYOUT).config, [tmp / "expert.zarr"],
                          RunConfig(run_dir=tmp / "policy", max_steps=20, **run))
    wm = train(WorldModelModule, world_model_profile("tiny", 1, LAYOUT).config, [tmp / "expert.zarr"],
                           RunConfig(run_dir=tmp / "wm", max_steps=20, **run))
    return {"policy": str(policy.last), "wm": str(wm.last), "dir": str(tmp)}


def histories(seeds, sim: bool = False) -> dict[str, np.ndarray]:
    obs = []
    for s in seeds:
        env = PushTEnv()
        env.reset(seed=s)
        o = observe(env, images=False, sim=sim)
        obs.append({k: np.stack([v, v]) for k, v in o.items()})
    return {k: np.stack([o[k] for o in obs]) for k in obs[0]}


def planner(ckpts, **kw) -> Planner:
    config = PlannerConfig(**{"action_low": LAYOUT.action.low, "action_high": LAYOUT.action.high, **kw})
    policy = PolicyModule.load_from_checkpoint(ckpts["policy"])
    return model_planner(config, WorldModelModule.load_from_checkpoint(ckpts["wm"]), build_reward(RewardSpec(), PUSHT), policy)


def gens(seeds, sampling_seed: int = 0):
    return [episode_generator(sampling_seed, s) for s in seeds]


def shows_the_chosen_future(mp4: Path) -> bool:
    """`gpc plan`'s first frame, for a task that overlays no state futures of its own (or image futures): a panel of
    four with the chosen candidate's predicted last step at the top right, framed in green."""
    import cv2

    cap = cv2.VideoCapture(str(mp4))
    ok, bgr = cap.read()
    cap.release()
    rgb = bgr[..., ::-1].astype(int)
    half = rgb.shape[0] // 2
    border = rgb[1, half + 8 : -8]  # the top-right tile's top edge
    return bool(ok) and border[:, 1].mean() > 120 and border[:, 0].mean() < 80 and border[:, 2].mean() < 80
