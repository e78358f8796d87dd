"""Shared fixtures: the real human Push-T data beside the checkout, when it is there."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

HUMAN_DATA = Path(os.environ.get("GPC_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")) / "pusht_human_train.zarr"


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Files with a slow (minutes-long) test first: `make test` deals whole files out in this order to two processes
    (`--no-loadscope-reorder`); a long file dealt out last would leave one core idle while it runs alone."""
    slow = {item.path for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: item.path not in slow)  # stable: the order inside a file is kept


@pytest.fixture(scope="session")
def human_data() -> Path:
    if not HUMAN_DATA.exists():
        pytest.skip(f"real Push-T data not found at {HUMAN_DATA} (it ships in ../shared beside the checkout)")
    return HUMAN_DATA


@pytest.fixture(scope="session")
def human_arrays(human_data: Path) -> dict:
    from gpc.datasets.store import EpisodeStore

    store = EpisodeStore.open(human_data)
    return {
        "state": store.read("state").astype("float64"),
        "action": store.read("action").astype("float64"),
        "keypoint": store.read("keypoint").astype("float64"),
        "n_contacts": store.read("n_contacts"),
        "episode_ends": store.episode_ends,
        "store": store,
    }


@pytest.fixture(scope="module")
def one_thread():
    """Tiny networks run fastest on one thread (and do not fight a busy machine for the second core);
    modules opt in with ``pytestmark = pytest.mark.usefixtures("one_thread")``."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)



@pytest.fixture(scope="session")
def tiny_pusht(tmp_path_factory):
    """A tiny keypoint policy and state world model on real expert episodes, shared by the fault tests (trained once)."""
    from faults import train_tiny

    return train_tiny(tmp_path_factory.mktemp("tiny_pusht"))


@pytest.fixture(scope="session")
def ckpts(tmp_path_factory) -> dict[str, str]:
    """A tiny keypoint policy and state world model for the planner tests (tests/tiny_planning.py; trained once)."""
    from tiny_planning import train_checkpoints

    return train_checkpoints(tmp_path_factory.mktemp("planners"))
