"""The baselines (V-GPS's IQL Q-function, a DreamerV3-style RSSM) and the planner seam they plug into, on the toy task."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
from toy_task import GOAL, LAYOUT, REACH, move

from gpc.datasets.errors import DataError
from gpc.harness.collection import CollectJob, collect
from gpc.harness.evaluation import EvalConfig, evaluate
from gpc.harness.recipes import GT_SIM, make_recipe
from gpc.models.ladi.config import ladi_profile
from gpc.models.ladi.module import LadiModule
from gpc.models.latent.config import latent_profile
from gpc.models.latent.module import LatentWorldModelModule
from gpc.models.latent.rssm import symexp
from gpc.models.planning import registry
from gpc.models.planning.config import PlannerConfig
from gpc.models.planning.planner import Rank
from gpc.models.planning.registry import PlannerKind, planner_names, register_planner
from gpc.models.policy.config import policy_profile
from gpc.models.policy.module import PolicyModule
from gpc.models.training.config import RunConfig
from gpc.models.training.trainer import train
from gpc.models.values.config import value_profile
from gpc.models.values.module import ValueModule, expectile_loss
from gpc.tasks import register_task

pytestmark = pytest.mark.usefixtures("one_thread")
SEEDS = tuple(range(100000, 100004))


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> dict[str, Path]:
    register_task(REACH)
    tmp = tmp_path_factory.mktemp("reach_values")
    collect(CollectJob(task="reach", out=tmp / "expert.zarr", episodes=12, images=False, max_steps=40))
    collect(CollectJob(task="reach", kind="explore", out=tmp / "explore.zarr", episodes=24, seed=500, images=False, max_steps=40))
    run = {"batch_size": 64, "progress": False, "accelerator": "cpu", "checkpoint_every": 1000}
    policy = train(PolicyModule, policy_profile("tiny", "state", LAYOUT).config, [tmp / "expert.zarr"],
                   RunConfig(run_dir=tmp / "policy", max_steps=60, **run))
    config = value_profile("tiny", "state", LAYOUT, (2, 4), lr=3e-3).config
    value = train(ValueModule, dataclasses.replace(config, discount=0.9), [tmp / "expert.zarr", tmp / "explore.zarr"],
                  RunConfig(run_dir=tmp / "value", max_steps=800, **run))  # 20 s on one thread
    return {"policy": policy.last, "value": value.last, "tmp": tmp}


def _reached(start: np.ndarray, chunk: np.ndarray) -> np.ndarray:
    position = start.copy()
    for action in chunk:
        position = move(position, action)
    return position


def test_q_prefers_the_chunk_that_brings_the_point_nearer_the_goal(trained):
    """Q, learned offline from expert and random episodes, orders chunks as the true reward of where they lead."""
    value = ValueModule.load_from_checkpoint(trained["value"])
    start = np.array([25.0, 75.0])
    history = {"state": np.array([[start, start]])}
    rng = np.random.default_rng(0)
    targets = rng.uniform(0.0, 100.0, size=(24, 2))
    chunks = np.repeat(targets[:, None], 4, axis=1)  # each chunk heads for one target for 4 steps
    chunks[0], chunks[1] = GOAL, (0.0, 100.0)  # straight at the goal; straight away from it
    q = value.q(history, torch.as_tensor(chunks[None], dtype=torch.float32))[0].numpy()
    true = np.array([-np.linalg.norm(_reached(start, c) - np.asarray(GOAL)) for c in chunks])  # the task's reward there
    assert q[0] - q[1] > 0.5 * (true[0] - true[1]), (q[:2], true[:2])  # (the true gap: 24; its Q adds what follows)
    ranks = lambda x: np.argsort(np.argsort(x))  # noqa: E731
    assert np.corrcoef(ranks(q), ranks(true))[0, 1] > 0.7, (q, true)


def test_iql_weights_the_value_towards_the_better_actions():
    """The expectile loss at tau 0.7 is minimised above the mean (V fits the better chunks' Q, not SARSA's average)."""
    q = torch.tensor([0.0, 0.0, 1.0, 1.0, 5.0])
    grid = torch.linspace(0.0, 5.0, 501)
    best = grid[torch.stack([expectile_loss(q - v, 0.7) for v in grid]).argmin()]
    assert float(q.mean()) < float(best) < float(q.max())
    assert abs(float(grid[torch.stack([expectile_loss(q - v, 0.5) for v in grid]).argmin()]) - float(q.mean())) < 0.011


def test_vgps_ranks_the_policys_proposals_by_q_and_records_its_settings(trained):
    recipe = make_recipe(trained["policy"], "vgps", world_model=str(trained["value"]), k=6)
    controller = recipe()
    obs = {"state": np.array([[[20.0, 80.0], [21.0, 79.0]]])}
    plan = controller.plan(obs, [torch.Generator().manual_seed(3)])
    proposals = controller.policy.sample_batch(obs, 6, [torch.Generator().manual_seed(3)])[:, :, 1:].float()
    expected = ValueModule.load_from_checkpoint(trained["value"]).q(obs, proposals)
    assert np.allclose(plan.scores, expected.numpy(), atol=1e-5) and int(plan.chosen[0]) == int(expected.argmax())
    summary = recipe.summary()
    assert summary["controller"] == "vgps K=6" and summary["planner"]["kind"] == "vgps" and "reward" not in summary
    result = evaluate(recipe, EvalConfig(seeds=SEEDS, task="reach", max_steps=20, batch=2))
    assert [e["seed"] for e in result["episodes"]] == list(SEEDS)


def test_vgps_refuses_what_it_cannot_score_with(trained):
    with pytest.raises(ValueError, match="value function, not the simulator"):
        make_recipe(trained["policy"], "vgps", world_model=GT_SIM)
    with pytest.raises(ValueError, match="needs --world-model CKPT, its value function"):
        make_recipe(trained["policy"], "vgps")
    with pytest.raises(DataError, match="policy"):  # a policy checkpoint where the value function belongs
        make_recipe(trained["policy"], "vgps", world_model=str(trained["policy"]))
    with pytest.raises(ValueError, match="vgps takes no steps"):
        PlannerConfig(kind="vgps", opt_steps=3)


class LastProposal(Rank):
    """A user's planner: always the policy's last proposal (scores rise with the index)."""

    def search(self, objective, obs, generators, timer):
        chunks, _, futures = super().search(objective, obs, generators, timer)
        return chunks, torch.arange(chunks.shape[1], dtype=torch.float32).expand(chunks.shape[:2]), futures


def test_a_users_planner_registers_by_name_and_runs_like_the_built_in_ones(trained, monkeypatch):
    with pytest.raises(ValueError, match="vgps"):  # the known names, the baselines among them
        make_recipe(trained["policy"], "last")
    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))  # this test's registration ends with it
    register_planner(PlannerKind("last", "test_baselines:LastProposal", uses_reward=False, load="gpc.models.values.module:load_value"))
    assert "last" in planner_names()
    recipe = make_recipe(trained["policy"], "last", world_model=str(trained["value"]), k=5)
    plan = recipe().plan({"state": np.array([[[20.0, 80.0], [21.0, 79.0]]])}, [torch.Generator().manual_seed(0)])
    assert int(plan.chosen[0]) == 4 and recipe.summary()["controller"] == "last K=5"


@pytest.mark.parametrize(("fixture", "bar"), [("latent", 0.4), pytest.param("latent_history", 0.5, marks=pytest.mark.extended)])
def test_the_rssm_imagines_the_rewards_its_posterior_reads_from_the_true_observations(trained, fixture, bar, request):
    """Along stored expert episodes' actions, the reward imagined with prior latents from the first observation agrees
    with the reward head on the posterior latents of the observations really reached, and with the true reward: over
    five episodes each errs well under half as much as predicting no change would. With a stacked history the
    episode's start is padded with its first observation, as the evaluation's history starts; the toy point has no
    velocity, so the earlier frame is an input it learns to ignore, and at the same steps it errs a little more
    (measured 6.7 against 4.6, "no change" 15.0)."""
    from gpc.datasets.store import EpisodeStore

    model = LatentWorldModelModule.load_from_checkpoint(request.getfixturevalue(fixture))
    net, pad = model.model, model.config.history - 1
    assert model.n_obs_steps == model.config.history
    store = EpisodeStore.open(trained["tmp"] / "expert.zarr")
    errors: dict[str, list[float]] = {"observed": [], "true": [], "still": []}
    for episode in range(5):
        start = int(store.episode_ends[episode - 1]) if episode else 0
        states, actions = store.read("state")[start : start + 12], store.read("action")[start : start + 12]
        padded = np.concatenate([states[:1]] * pad + [states])
        imagined = model.imagine({"state": padded[None, : pad + 1]}, torch.as_tensor(actions[None, None, :11]))[0, 0].numpy()
        embedding = model._embed({"state": torch.as_tensor(padded[None])})[0]
        assert len(embedding) == len(states)
        h, _ = net.initial(1, embedding.device)
        _, z = net.observe(h, embedding[:1], mode=True)
        observed = []
        with torch.no_grad():
            for t in range(1, 12):
                h = net.step(h, z, model.normalizer.normalize("action", torch.as_tensor(actions[None, t - 1])))
                _, z = net.observe(h, embedding[t : t + 1], mode=True)
                observed.append(float(symexp(net.heads(h, z)[1])[0]) * model.config.reward_scale)
        true = -np.linalg.norm(states[1:12] - np.asarray(GOAL), axis=1)  # the task's reward there
        errors["observed"].append(float(np.abs(imagined - np.asarray(observed)).mean()))
        errors["true"].append(float(np.abs(imagined - true).mean()))
        errors["still"].append(float(np.abs(true - true[0]).mean()))
    still = np.mean(errors["still"])
    assert np.mean(errors["observed"]) < bar * still and np.mean(errors["true"]) < bar * still, errors


@pytest.fixture(scope="module")
def latent(trained) -> Path:
    tmp = trained["tmp"]
    config = latent_profile("tiny", "state", LAYOUT, lr=3e-3).config
    run = RunConfig(run_dir=tmp / "latent", max_steps=800, batch_size=32, progress=False, accelerator="cpu", checkpoint_every=1000)
    return train(LatentWorldModelModule, config, [tmp / "expert.zarr", tmp / "explore.zarr"], run).last  # 35 s on one thread


def train_latent_history(trained, steps: int) -> Path:
    """The RSSM whose posterior reads the policy's two observations, stacked."""
    tmp = trained["tmp"]
    config = dataclasses.replace(latent_profile("tiny", "state", LAYOUT, lr=3e-3).config, history=2)
    run = RunConfig(run_dir=tmp / f"latent2-{steps}", max_steps=steps, batch_size=32, progress=False, accelerator="cpu",
                    checkpoint_every=1000)
    return train(LatentWorldModelModule, config, [tmp / "expert.zarr", tmp / "explore.zarr"], run).last


@pytest.fixture(scope="module")
def latent_history(trained) -> Path:
    return train_latent_history(trained, 800)


def test_a_stacked_history_reads_the_observation_before_now_and_only_that(trained):
    """With history 2 the first posterior reads the previous observation too: moving it changes the imagined rewards,
    and the one before it (outside the history) changes nothing. Which frames it reads is the wiring's, not the
    training's: a few steps (the trained model learns to weigh the earlier frame little, on a point without velocity)."""
    model = LatentWorldModelModule.load_from_checkpoint(train_latent_history(trained, 20))
    chunks = torch.tensor([[[list(GOAL)] * 8]])
    now = np.array([40.0, 60.0])

    def imagined(*before: np.ndarray) -> np.ndarray:
        return model.imagine({"state": np.array([[*before, now]])}, chunks)[0, 0].numpy()

    still, moving = imagined(now), imagined(np.array([10.0, 90.0]))
    assert np.abs(still - moving).max() > 1e-3, (still, moving)
    np.testing.assert_array_equal(imagined(np.array([0.0, 0.0]), now), still)


def test_dreamer_ranks_the_chunk_that_reaches_the_goal_first_and_plugs_in_by_name(trained, latent):
    model = LatentWorldModelModule.load_from_checkpoint(latent)
    start = np.array([25.0, 75.0])
    chunks = torch.tensor([[[list(GOAL)] * 8, [[0.0, 100.0]] * 8]])
    scores = model.score(model.imagine({"state": np.array([[start, start]])}, chunks))[0]
    assert float(scores[0]) > float(scores[1]), scores
    recipe = make_recipe(trained["policy"], "dreamer", world_model=str(latent), k=5)
    assert recipe.summary()["controller"] == "dreamer K=5" and "reward" not in recipe.summary()
    result = evaluate(recipe, EvalConfig(seeds=SEEDS[:2], task="reach", max_steps=16, batch=2))
    assert [e["seed"] for e in result["episodes"]] == list(SEEDS[:2])
    with pytest.raises(DataError, match="value"):  # a value checkpoint where the latent model belongs
        make_recipe(trained["policy"], "dreamer", world_model=str(trained["value"]))


@pytest.fixture(scope="module")
def ladi(trained) -> Path:
    tmp = trained["tmp"]
    policy = PolicyModule.load_from_checkpoint(trained["policy"])
    profile = ladi_profile("tiny", LAYOUT, str(trained["policy"]), policy.config.encoder, (2, 8), lr=3e-3)
    run = RunConfig(run_dir=tmp / "ladi", max_steps=600, batch_size=64, progress=False, accelerator="cpu", checkpoint_every=1000)
    return train(LadiModule, profile.config, [tmp / "expert.zarr", tmp / "explore.zarr"], run).last


def test_ladi_predicts_where_a_chunk_leads_in_the_frozen_encoders_latents_and_ranks_by_it(trained, ladi):
    """The latents it samples decode (the state policy's encoder is its normaliser) to the true positions, far
    closer than "nothing moves", for chunks like the data's (a random target each step, as the exploration
    collector draws them; and straight at the goal, as the expert goes), and its scores order the chunks as the
    true reward where they lead."""
    model = LadiModule.load_from_checkpoint(ladi)
    start = np.array([30.0, 70.0])
    chunks = np.random.default_rng(0).uniform(0.0, 100.0, size=(24, 8, 2))
    chunks[0] = GOAL
    latents = model.predict({"state": np.array([[start, start]])}, torch.as_tensor(chunks[None], dtype=torch.float32))[0, :, -1]
    net = model.ema.model if model.ema is not None else model.model
    normalised = (latents + 1.0) / 2.0 * (net.high - net.low) + net.low
    predicted = model.normalizer.unnormalize("state", normalised).numpy()
    true = np.stack([_reached(start, c) for c in chunks])
    error, still = np.linalg.norm(predicted - true, axis=1), np.linalg.norm(true - start, axis=1)
    assert np.median(error) < 0.5 * np.median(still) and error[0] < 0.3 * still[0], (predicted, true)
    scores = model.rewards(latents).numpy()
    ranks = lambda x: np.argsort(np.argsort(x))  # noqa: E731
    truth = -np.linalg.norm(true - np.asarray(GOAL), axis=1)
    assert np.corrcoef(ranks(scores), ranks(truth))[0, 1] > 0.7, (scores, truth)
    recipe = make_recipe(trained["policy"], "ladi", world_model=str(ladi), k=3)
    assert recipe.summary()["controller"] == "ladi K=3"
    plan = recipe().plan({"state": np.array([[start, start]])}, [torch.Generator().manual_seed(1)])
    again = recipe().plan({"state": np.array([[start, start]])}, [torch.Generator().manual_seed(1)])
    assert np.array_equal(plan.scores, again.scores)  # the futures' noise is fixed: a decision repeats


def test_ladi_encodes_each_stored_frame_once_as_its_frozen_image_encoder_reads_it_at_a_decision(tmp_path):
    """With an image policy's encoder, windows read features computed once per stored frame (not 10 frames per
    window per step): the loss on them equals the loss on the same window's frames read through the encoder in
    eval mode (as at a decision), so the features sit at the right steps and scale."""
    from test_policy import make_store
    from test_policy import tiny as tiny_policy

    from gpc.datasets.datamodule import EpisodeDataModule
    from gpc.datasets.windows import WindowDataset
    from gpc.models.ladi.module import FEATURE_KEY, IMAGE_KEY
    from gpc.tasks.pusht import LAYOUT as PUSHT

    store = make_store(tmp_path / "demo.zarr", episodes=3, length=30)
    run = RunConfig(run_dir=tmp_path / "vpolicy", max_steps=2, batch_size=8, progress=False, accelerator="cpu")
    policy_ckpt = train(PolicyModule, tiny_policy("image"), [store], run).last
    policy = PolicyModule.load_from_checkpoint(policy_ckpt)
    config = ladi_profile("tiny", PUSHT, str(policy_ckpt), policy.config.encoder, (2, 8)).config
    windows = LadiModule.data_config(config, (str(store),), dataclasses.replace(run, run_dir=tmp_path / "ladi"), (0, 0.0))
    data = EpisodeDataModule(windows)
    config = LadiModule.fit_to_data(config, data.arrays, str(store), resumed=False)
    module = LadiModule.from_data(config, data, {})
    frames = WindowDataset(data.arrays, data.train_episodes, windows.spec, dict(data.steps))
    module.prepare(data)
    assert IMAGE_KEY not in data.steps and data.arrays.data[FEATURE_KEY].shape[0] == 90
    features = WindowDataset(data.arrays, data.train_episodes, windows.spec, data.steps)
    module.eval()
    for i in (0, len(frames) // 2, len(frames) - 1):
        losses = []
        for window in (frames[i], features[i]):
            torch.manual_seed(i)
            losses.append(module.loss({k: v[None] for k, v in window.items()})[0])
        assert float(losses[0]) == pytest.approx(float(losses[1]), rel=1e-5, abs=1e-6)


def test_the_ranking_probe_scores_the_truth_perfectly_and_its_reverse_as_the_worst_pick(trained):
    """`gpc eval ranking`'s probe on BC's states: the simulator ranking its own replays agrees with the truth exactly
    (correlation 1, always the best pick, no regret); the same scores negated correlate -1 and always pick the worst,
    giving up more than a pick at random."""
    from gpc.harness.rank_probe import probe_ranking

    class Negated:
        def __init__(self, scorer):
            self.scorer, self.obs_keys, self.n_obs_steps = scorer, scorer.obs_keys, scorer.n_obs_steps

        def objective(self, obs, timer, episodes=None):
            score = self.scorer.objective(obs, timer, episodes)
            return lambda chunks: tuple(-x if i == 0 else x for i, x in enumerate(score(chunks)))

    truth, reverse = make_recipe(trained["policy"], GT_SIM, k=12)(), make_recipe(trained["policy"], GT_SIM, k=12)()
    reverse.scorer = Negated(reverse.scorer)
    summary = probe_ranking({"truth": truth, "reverse": reverse}, REACH, SEEDS[:2], k=12, max_steps=16, batch=2)
    assert summary["decisions"] >= 2 and summary["random_regret"] > 0
    right, wrong = summary["scorers"]["truth"], summary["scorers"]["reverse"]
    assert right["spearman_mean"] == pytest.approx(1.0) and right["picks_best"] == 1.0 and right["regret"] == 0.0
    assert wrong["spearman_mean"] == pytest.approx(-1.0) and wrong["picks_best"] == 0.0
    assert wrong["regret"] > summary["random_regret"] and wrong["margin_kept"] < 0
