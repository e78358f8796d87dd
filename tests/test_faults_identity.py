"""A run's identity is every setting that changes its numbers: resume, compare, record and train refuse to mix two runs."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import pytest
from faults import digest, gpc, inline, one_line

from gpc.datasets.store import EpisodeStore

pytestmark = pytest.mark.usefixtures("one_thread")

EPISODES = ["--seeds", "100000:100002", "--max-steps", "5", "--batch", "2"]


def _eval(models: dict[str, Path], out: Path, *extra: str) -> tuple[int, str]:
    return inline("eval", str(models["policy"]), *EPISODES, "--out", str(out), *extra)


def test_resume_is_refused_for_another_sampler_or_reward_aggregate(tiny_pusht, tmp_path):
    bc = tmp_path / "bc"
    assert _eval(tiny_pusht, bc)[0] == 0
    before = digest(bc)
    one_line(_eval(tiny_pusht, bc, "--method", "ddpm", "--resume"), 2, str(bc),
             "controller.sampling: absent there, {'method': 'ddpm'} here")
    one_line(_eval(tiny_pusht, bc, "--steps", "2", "--resume"), 2, "controller.sampling: absent there, {'steps': 2} here")
    assert _eval(tiny_pusht, bc, "--method", "ddim", "--steps", "4", "--resume")[0] == 0  # the checkpoint's own: the same run
    assert digest(bc) == before

    rank = tmp_path / "rank"
    plan = ["--planner", "rank", "-K", "2", "--world-model", str(tiny_pusht["wm"])]
    assert _eval(tiny_pusht, rank, *plan)[0] == 0
    before = digest(rank)
    one_line(_eval(tiny_pusht, rank, *plan, "--reward-aggregate", "discounted", "--resume"), 2, str(rank),
             "controller.reward_aggregate: absent there, discounted here")
    assert digest(rank) == before


def test_compare_tells_samplers_apart_and_never_joins_them(tiny_pusht, tmp_path):
    ddim, ddpm = tmp_path / "ddim" / "bc", tmp_path / "ddpm" / "bc"
    assert _eval(tiny_pusht, ddim)[0] == 0
    assert _eval(tiny_pusht, ddpm, "--method", "ddpm")[0] == 0
    assert json.loads((ddpm / "summary.json").read_text())["controller"]["controller"] == "bc [ddpm]"
    out = tmp_path / "c.md"
    assert inline("compare", str(ddpm), "--baseline", str(ddim), "--out", str(out))[0] == 0
    labels = [row["label"] for row in json.loads(out.with_suffix(".json").read_text())["rows"]]
    assert labels == ["bc", "bc [ddpm]"]  # two controllers, two rows

    later = tmp_path / "later"  # the same policy on more seeds, sampled otherwise: not one run over their union
    assert inline("eval", str(tiny_pusht["policy"]), "--seeds", "100002:100004", "--max-steps", "5", "--batch", "2",
                  "--out", str(later))[0] == 0
    joined = f"{ddpm}+{later}"
    one_line(inline("compare", joined, "--baseline", joined, "--out", str(tmp_path / "j.md")), 2, joined,
             "ran another controller", "controller.sampling: {'method': 'ddpm'} there, absent here")
    assert not (tmp_path / "j.md").exists()


def test_record_refuses_to_resume_a_store_with_another_sampler(tiny_pusht, tmp_path):
    store = tmp_path / "bc.zarr"
    args = ["record", str(tiny_pusht["policy"]), "--max-steps", "5", "--out", str(store), "--seed", "60000"]
    assert inline(*args, "--episodes", "1")[0] == 0
    attrs = EpisodeStore.open(store).attrs["collector"]
    assert attrs["checkpoints"] == {str(tiny_pusht["policy"]): digest(tiny_pusht["policy"])[tiny_pusht["policy"].name]}
    before = digest(store)
    one_line(inline(*args, "--episodes", "2", "--method", "ddpm"), 2, str(store), "holds data of another kind",
             "collector.sampling: absent there, {'method': 'ddpm'} here")
    assert digest(store) == before


def test_train_resume_is_refused_for_other_data_or_settings(tiny_pusht, tmp_path):
    data, other, run = tmp_path / "data.zarr", tmp_path / "other.zarr", tmp_path / "run"
    shutil.copytree(tiny_pusht["store"], data)
    shutil.copytree(tiny_pusht["store"], other)
    _drop_last_episode(other)

    def train(*extra: str) -> tuple[int, str]:
        return inline("train", "policy", "--obs", "keypoints", "--profile", "tiny", "--batch-size", "8", "--accelerator", "cpu",
                      "--no-progress", "--out", str(run), *extra)

    assert train("--dataset", str(data), "--max-steps", "2")[0] == 0
    before = digest(run)
    one_line(train("--dataset", str(other), "--max-steps", "3", "--resume"), 2, str(run / "checkpoints"),
             f"--dataset {other} is not the data the run trained on ({data} then")
    one_line(train("--dataset", str(data), "--dataset", str(other), "--max-steps", "3", "--resume"), 2,
             f"the run trained on --dataset {data}, not {data} {other}")
    one_line(train("--dataset", str(data), "--max-steps", "3", "--lr", "0.5", "--resume"), 2, "config.optim.lr: 0.003 there, 0.5 here")
    one_line(train("--dataset", str(data), "--max-steps", "3", "--seed", "1", "--resume"), 2, "seed: 0 there, 1 here")
    one_line(train("--dataset", str(data), "--max-steps", "3", "--batch-size", "4", "--resume"), 2, "batch_size: 8 there, 4 here")
    _drop_last_episode(data)  # the same path, other content
    one_line(train("--dataset", str(data), "--max-steps", "3", "--resume"), 2, f"--dataset {data} is not the data the run trained on")
    assert digest(run) == before
    # the data it trained on, copied elsewhere, and a larger step budget: the same run
    assert train("--dataset", str(tiny_pusht["store"]), "--max-steps", "3", "--resume")[0] == 0


def _drop_last_episode(path: Path) -> None:
    """The store without its last episode, written again by the store's own writer (as a user re-collecting fewer would)."""
    src = EpisodeStore.open(path)
    episodes, seeds, scores = [src.episode(i) for i in range(src.n_episodes - 1)], src.episode_seeds(), src.episode_scores()
    attrs = src.attrs
    shutil.rmtree(path)
    dst = EpisodeStore.create(path, {k: v for k, v in attrs.items() if k != "gpc_format"})
    for i, ep in enumerate(episodes):
        dst.append_episode(ep, seed=int(seeds[i]), score=float(scores[i]))  # type: ignore[index]


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_compare_refuses_a_score_that_is_no_number_before_writing(tiny_pusht, tmp_path, bad):
    res = tmp_path / "r"
    assert _eval(tiny_pusht, res)[0] == 0
    rows = json.loads((res / "episodes.json").read_text())
    rows[1]["score"] = bad
    (res / "episodes.json").write_text(json.dumps(rows))
    out = tmp_path / "c.md"
    one_line(gpc("compare", str(res), "--baseline", str(res), "--out", str(out)), 2, str(res / "episodes.json"),
             f"seed {rows[1]['seed']}", f"score {bad}")
    assert not any(tmp_path.glob("c.*"))
