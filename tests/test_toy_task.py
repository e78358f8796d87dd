"""A task gpc.models has never heard of (tests/toy_task.py) goes through collection, training and every planner."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import torch
from toy_task import GOAL, LAYOUT, REACH

from gpc.datasets.errors import DataError
from gpc.harness.collection import CollectJob, collect
from gpc.harness.comparison import compare_runs
from gpc.harness.evaluation import EvalConfig, evaluate, write_results
from gpc.harness.recipes import GT_SIM, make_recipe
from gpc.models.planning.config import PLANNERS
from gpc.models.policy.config import policy_profile
from gpc.models.policy.module import PolicyModule
from gpc.models.training.config import RunConfig
from gpc.models.training.trainer import train
from gpc.models.world_models.module import WorldModelModule
from gpc.models.world_models.profiles import world_model_profile
from gpc.tasks import get_task, register_task, task_names

pytestmark = pytest.mark.usefixtures("one_thread")
SEEDS = tuple(range(100000, 100006))


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> dict[str, Path]:
    register_task(REACH)
    tmp = tmp_path_factory.mktemp("reach")
    collect(CollectJob(task="reach", out=tmp / "expert.zarr", episodes=12, images=False, max_steps=40))
    collect(CollectJob(task="reach", kind="explore", out=tmp / "explore.zarr", episodes=12, seed=500, images=False, max_steps=40))
    run = {"batch_size": 32, "progress": False, "accelerator": "cpu", "checkpoint_every": 1000}
    policy = train(PolicyModule, policy_profile("tiny", "state", LAYOUT).config, [tmp / "expert.zarr"],
                   RunConfig(run_dir=tmp / "policy", max_steps=60, **run))
    wm = train(WorldModelModule, world_model_profile("tiny", 1, LAYOUT).config, [tmp / "expert.zarr", tmp / "explore.zarr"],
               RunConfig(run_dir=tmp / "wm", max_steps=400, **run))
    return {"policy": policy.last, "wm": wm.last, "tmp": tmp}


def test_the_toy_task_is_registered_and_its_stores_say_so(trained):
    assert "reach" in task_names() and get_task("reach") is REACH
    from gpc.datasets.store import EpisodeStore

    store = EpisodeStore.open(trained["tmp"] / "explore.zarr")
    assert store.attrs["task"] == "reach" and store.keys == ["action", "state"] and store.n_episodes == 12
    assert PolicyModule.load_from_checkpoint(trained["policy"]).config.task == "reach"
    config = WorldModelModule.load_from_checkpoint(trained["wm"]).config
    assert config.dynamics.state_dim == 2 and config.dynamics.object_frame == ()  # no angle: world coordinates


def test_worker_processes_and_commands_know_the_toy_task(trained, tmp_path, monkeypatch):
    """A task registered by hand reaches spawned workers (collection and evaluation give what one process gives),
    and one named in $GPC_TASKS reaches the `gpc` command."""
    one = collect(CollectJob(task="reach", out=tmp_path / "one.zarr", episodes=4, images=False, max_steps=40))
    two = collect(CollectJob(task="reach", out=tmp_path / "two.zarr", episodes=4, images=False, max_steps=40, workers=2))
    from gpc.datasets.store import EpisodeStore

    a, b = EpisodeStore.open(tmp_path / "one.zarr"), EpisodeStore.open(tmp_path / "two.zarr")
    assert one.written == two.written == 4 and (a.read("state") == b.read("state")).all()
    config = EvalConfig(seeds=SEEDS, task="reach", max_steps=20, batch=2)
    recipe = make_recipe(trained["policy"], "rank", world_model=str(trained["wm"]), k=3)
    alone, spread = evaluate(recipe, config), evaluate(recipe, dataclasses.replace(config, workers=2))
    assert alone["episodes"] == spread["episodes"]
    from typer.testing import CliRunner

    from gpc.cli.main import app

    monkeypatch.setenv("GPC_TASKS", "toy_task:REACH")
    monkeypatch.setattr("gpc.tasks._discovered", [])
    monkeypatch.setattr("gpc.tasks._REGISTRY", {})
    res = CliRunner().invoke(app, ["collect", "--task", "reach", "--out", str(tmp_path / "cli.zarr"), "--episodes", "2",
                                   "--no-images", "--max-steps", "30"])
    assert res.exit_code == 0, res.output
    assert EpisodeStore.open(tmp_path / "cli.zarr").attrs["task"] == "reach"


def test_the_world_model_learns_the_toy_dynamics(trained):
    model = WorldModelModule.load_from_checkpoint(trained["wm"])
    history = torch.tensor([[20.0, 80.0], [20.0, 80.0]])  # where episodes start, heading for the goal
    actions = torch.tensor([[list(GOAL)] * 4])
    pred = model.rollout(history, actions)[0]
    true = REACH.simulator().rollout(history, actions)[0]
    still = (history[-1] - true).norm(dim=-1)  # "nothing moves": 3, 6, 9, 12
    assert ((pred - true).norm(dim=-1) < 0.3 * still).all(), (pred, true)


@pytest.mark.parametrize("planner", PLANNERS + (GT_SIM,))
def test_every_planner_runs_closed_loop_on_the_toy_task(trained, planner, tmp_path):
    small = {"rank": (4, None), "opt": (None, 2), "rank-opt": (3, 2), "cem": (8, 2), "mppi": (8, 2), "grad": (4, 2),
             GT_SIM: (4, None)}[planner]
    recipe = make_recipe(trained["policy"], planner, world_model=None if planner == GT_SIM else str(trained["wm"]),
                         k=small[0], m=small[1])
    config = EvalConfig(seeds=SEEDS, task="reach", max_steps=30, batch=3)
    result = evaluate(recipe, config)
    assert [r["seed"] for r in result["episodes"]] == list(SEEDS)
    assert all(0.0 <= r["score"] <= 1.0 and r["steps"] >= 1 for r in result["episodes"])
    assert result["time_share"] and 0.0 <= result["mean_score"] <= 1.0
    planned = recipe.summary()["planner"]  # the sizes asked for reached the planner
    kind = "rank" if planner == GT_SIM else planner
    assert (planned["kind"], planned["num_proposals"]) == (kind, small[0] or 1)
    assert planned["opt_steps"] == (small[1] or 0)  # ascent steps, or CEM's and MPPI's iterations
    bc = evaluate(make_recipe(trained["policy"]), config)
    if planner == GT_SIM:  # the true simulator's pick of four, by the chunk's reward, not below the policy's one draw
        assert result["mean_score"] >= bc["mean_score"] - 0.02, (result["mean_score"], bc["mean_score"])
    write_results(bc, tmp_path / "bc", "bc")
    result["controller"] = recipe.summary()
    write_results(result, tmp_path / "planner", recipe.label)
    table = compare_runs(tmp_path / "bc", [tmp_path / "planner"])
    assert [row["label"] for row in table["rows"]] == ["bc", recipe.label]
    # a protocol of fewer seeds read from the same runs: the rows are those seeds' figures alone
    part = compare_runs(tmp_path / "bc", [tmp_path / "planner"], seeds=list(SEEDS[:2]))
    assert part["rows"][1]["seeds"] == 2 and part["seeds"] == [SEEDS[0], SEEDS[1]]
    assert part["rows"][1]["score"] == pytest.approx(sum(r["score"] for r in result["episodes"][:2]) / 2)
    with pytest.raises(DataError, match="lacks seed"):
        compare_runs(tmp_path / "bc", [tmp_path / "planner"], seeds=[SEEDS[-1] + 1])
    assert json.loads((tmp_path / "planner" / "summary.json").read_text())["config"]["task"] == "reach"


def test_the_toy_ceiling_ranks_by_the_true_outcome(trained):
    """gt-sim on the toy task picks the proposal whose true end point is nearest the goal."""
    recipe = make_recipe(trained["policy"], GT_SIM, k=8)
    controller = recipe()
    env = REACH.make_env("fixed")
    env.reset(seed=SEEDS[0])
    obs = REACH.observe(env, False, True)
    batch = {k: v[None, None].repeat(controller.n_obs_steps, axis=1) for k, v in obs.items()}
    from gpc.harness.evaluation import episode_generator

    plan = controller.plan(batch, [episode_generator(0, SEEDS[0])])
    assert plan.scores is not None and int(plan.chosen[0]) == int(plan.scores[0].argmax())
    assert plan.scores.shape == (1, 8) and (plan.scores <= 0).all()  # -distance to the goal at the chunk's end
    end = REACH.simulator().rollout(torch.as_tensor(obs["sim"][None]), torch.as_tensor(plan.chunk))[0, -1]
    assert abs(-float((end - torch.tensor(GOAL)).norm()) - float(plan.scores[0].max())) < 1e-4


def test_a_task_names_its_own_state_reward_and_planners_score_with_it():
    """A task's reward on predicted states is its choice: one registered by name replaces registration."""
    from gpc.harness.recipes import RewardSpec, build_reward
    from gpc.models.rewards.registration import RegistrationReward
    from gpc.models.rewards.state import register_state_reward

    class FarRight(torch.nn.Module):  # rewards the point for going right, whatever the goal
        def forward(self, futures: torch.Tensor, goal: torch.Tensor | None = None) -> torch.Tensor:
            return futures[:, -1, 0]

    register_state_reward("far-right", lambda layout, config: FarRight())
    assert isinstance(build_reward(RewardSpec(), REACH), RegistrationReward)
    custom = dataclasses.replace(REACH, state_reward="far-right")
    futures = torch.tensor([[[10.0, 5.0]], [[30.0, 5.0]]])
    assert build_reward(RewardSpec(), custom)(futures).tolist() == [10.0, 30.0]
    with pytest.raises(ValueError, match="unknown state reward 'nowhere'"):
        build_reward(RewardSpec(), dataclasses.replace(REACH, state_reward="nowhere"))
