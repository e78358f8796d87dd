"""Vision planning end to end: an image policy, the visual world model and the learned image reward through
`gpc eval`, the vision ceiling (the true simulator ranking the image policy's proposals) and the ascent probe."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from tiny_planning import shows_the_chosen_future
from typer.testing import CliRunner

from gpc.cli.main import app
from gpc.harness.collection import CollectJob, collect
from gpc.harness.evaluation import episode_generator
from gpc.harness.recipes import RewardSpec, build_reward
from gpc.models.planning.config import PlannerConfig
from gpc.models.planning.planner import model_planner
from gpc.models.policy.config import policy_profile
from gpc.models.policy.module import PolicyModule
from gpc.models.rewards.learned import RewardPredictorModule, reward_profile
from gpc.models.training.config import RunConfig
from gpc.models.training.trainer import train
from gpc.models.world_models.module import WorldModelModule
from gpc.models.world_models.profiles import world_model_profile
from gpc.tasks import get_task
from gpc.tasks.pusht import LAYOUT, SimulatorModel
from gpc.tasks.pusht.env import PushTEnv
from gpc.tasks.pusht.record import observe

pytestmark = pytest.mark.usefixtures("one_thread")


def vision_ceiling_delivers_its_predictions(policy: PolicyModule) -> None:
    """gt-sim over an image policy: the chunk it picks delivers the reward it predicted (frames in, true states scored)."""
    reward = build_reward(RewardSpec(), get_task("pusht"))
    p = model_planner(PlannerConfig(kind="rank", num_proposals=4), SimulatorModel(), reward, policy)
    assert "img" in p.obs_keys
    env = PushTEnv()
    env.reset(seed=100002)
    o = observe(env, images=True, sim=True)
    plan = p.plan({k: np.stack([v] * policy.config.n_obs_steps)[None] for k, v in o.items()}, [episode_generator(0, 100002)])
    states = []
    for action in plan.chunk[0]:
        env.step(action)
        states.append(env.sim.state())
    delivered = reward(torch.as_tensor(np.array(states), dtype=torch.float32)[None])
    assert float(delivered[0]) == pytest.approx(float(plan.scores[0, plan.chosen[0]]), abs=1e-3)



def test_vision_pipeline_plans_with_frames(tiny_pusht, tmp_path):
    """Image policy + visual world model + learned image reward, end to end through `gpc eval`."""
    collect(CollectJob(task="pusht", out=tmp_path / "img.zarr", episodes=3, images=True, max_steps=40))
    data, run = [tmp_path / "img.zarr"], dict(batch_size=8, progress=False, accelerator="cpu")
    policy = train(PolicyModule, policy_profile("tiny", "image", LAYOUT).config, data,
                   RunConfig(run_dir=tmp_path / "p", max_steps=3, **run))
    wm = train(WorldModelModule, world_model_profile("tiny", 1, LAYOUT, obs="image").config, data,
                           RunConfig(run_dir=tmp_path / "w", max_steps=3, **run))
    reward_config = reward_profile("tiny", LAYOUT).config
    reward = train(RewardPredictorModule, reward_config, data, RunConfig(run_dir=tmp_path / "r", max_steps=3, **run))
    out = tmp_path / "vision"
    res = CliRunner().invoke(app, ["eval", str(policy.last), "--planner", "rank", "-K", "3", "--world-model", str(wm.last),
                                   "--reward", "learned", "--reward-checkpoint", str(reward.last),
                                   "--seeds", "100000:100002", "--max-steps", "16", "--batch", "2", "--out", str(out)])
    assert res.exit_code == 0, res.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["controller"]["controller"] == "rank K=3" and 0.0 <= summary["mean_score"] <= 1.0
    assert set(summary["time_share"]) == {"policy", "world_model", "reward"}
    # rollouts' precision is part of the run: float32 (this model does not ask for bf16) is recorded by omission, so a
    # pinned 32-true run resumes it, and bf16 rollouts (other numbers) are refused in one line that says so
    assert "rollouts" not in summary["controller"]
    again = ["eval", str(policy.last), "--planner", "rank", "-K", "3", "--world-model", str(wm.last), "--reward", "learned",
             "--reward-checkpoint", str(reward.last), "--seeds", "100000:100002", "--max-steps", "16", "--batch", "2",
             "--out", str(out), "--resume"]
    assert CliRunner().invoke(app, [*again, "--precision", "32-true"]).exit_code == 0
    before = (out / "summary.json").read_bytes()
    mixed = CliRunner().invoke(app, [*again, "--precision", "bf16-mixed"])
    assert mixed.exit_code != 0 and len(mixed.output.strip().splitlines()) == 1
    assert "controller.rollouts: absent there, bfloat16 here" in mixed.output and (out / "summary.json").read_bytes() == before
    wrong = CliRunner().invoke(app, [*again, "--precision", "bf16"])
    assert wrong.exit_code != 0 and "--precision 'bf16': use one of bf16-auto, 32-true, bf16-mixed" in wrong.output
    # `gpc plan` shows image futures: the chosen one's predicted last frame beside the scene (it once crashed on them)
    res = CliRunner().invoke(app, ["plan", str(policy.last), "--world-model", str(wm.last), "--reward", "learned",
                                   "--reward-checkpoint", str(reward.last), "-K", "3", "--seed", "100001", "--max-steps", "8",
                                   "--out", str(tmp_path / "plan")])
    assert res.exit_code == 0, res.output
    assert shows_the_chosen_future(tmp_path / "plan" / "seed100001.mp4")
    # the vision ceiling: the true simulator ranks the image policy's proposals, and delivers what it predicted
    vision_ceiling_delivers_its_predictions(PolicyModule.load_from_checkpoint(policy.last))
    ceiling = CliRunner().invoke(app, ["eval", str(policy.last), "--planner", "gt-sim", "-K", "3", "--seeds", "100000:100002",
                                       "--max-steps", "16", "--batch", "2", "--out", str(tmp_path / "ceiling")])
    assert ceiling.exit_code == 0, ceiling.output
    assert json.loads((tmp_path / "ceiling" / "summary.json").read_text())["controller"]["controller"] == "gt-sim K=3"
    # the ascent probe through the visual model and the learned reward (its model error compares frames)
    res = CliRunner().invoke(app, ["eval", "ascent", str(policy.last), "--planner", "opt", "-M", "2", "--world-model", str(wm.last),
                                   "--reward", "learned", "--reward-checkpoint", str(reward.last), "--seeds", "200000",
                                   "--max-steps", "8", "--out", str(tmp_path / "ascent.md")])
    assert res.exit_code == 0, res.output
    report = json.loads((tmp_path / "ascent.json").read_text())
    assert report["decisions"] == 1 and 0.0 < report["model_error"]["start_mean"] < 1.0  # pixel RMSE in [0, 1] units
    truth = report["reward_on_true_frames"]  # the learned reward read on the rendered true frames: a finite gain
    assert truth is not None and math.isfinite(truth["gain_mean"]) and 0.0 <= truth["share_up"] <= 1.0
    assert report["selection"] is None  # one candidate: nothing is picked
    # a visual world model cannot plan for a keypoint policy: one line naming both
    bad = CliRunner().invoke(app, ["eval", str(tiny_pusht["policy"]), "--planner", "rank", "--world-model", str(wm.last),
                                   "--seeds", "100000", "--out", str(tmp_path / "bad")])
    assert bad.exit_code != 0 and "a visual world model cannot plan for a keypoints policy" in bad.output
    assert len(bad.output.strip().splitlines()) == 1
