import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from gpc.datasets.errors import DataError
from gpc.datasets.store import EpisodeStore

ROOT = Path(__file__).resolve().parents[1]


def _episode(i: int, length: int) -> dict[str, np.ndarray]:
    return {
        "state": np.full((length, 5), i, dtype=np.float32),
        "action": np.full((length, 2), -i, dtype=np.float32),
        "img": np.full((length, 8, 8, 3), i % 250, dtype=np.uint8),
    }


def test_roundtrip_in_diffusion_policy_layout(tmp_path):
    path = tmp_path / "s.zarr"
    store = EpisodeStore.create(path, {"task": "pusht", "collector": {"kind": "expert"}})
    for i, n in enumerate([3, 5, 2]):
        store.append_episode(_episode(i, n), seed=100 + i, score=0.5)
    again = EpisodeStore.open(path)
    assert (path / ".zgroup").exists() and (path / "data" / "state" / ".zarray").exists()  # zarr format 2
    np.testing.assert_array_equal(again.episode_ends, [3, 8, 10])
    np.testing.assert_array_equal(again.episode_seeds(), [100, 101, 102])
    assert again.keys == ["action", "img", "state"]
    ep = again.episode(1)
    assert ep["state"].shape == (5, 5) and np.all(ep["state"] == 1) and np.all(ep["action"] == -1)
    assert again.attrs["task"] == "pusht" and again.attrs["gpc_format"] == 2


def test_reads_diffusion_policy_store_as_is(human_data):
    store = EpisodeStore.open(human_data)
    assert store.n_episodes == 186 and store.n_steps == 22972
    assert set(store.keys) == {"action", "img", "keypoint", "n_contacts", "state"}
    assert store.episode_seeds() is None
    assert store.episode(0)["state"].shape == (161, 5)


def test_bad_appends_are_refused_and_leave_the_store_intact(tmp_path):
    store = EpisodeStore.create(tmp_path / "s.zarr", {"task": "pusht"})
    store.append_episode(_episode(0, 4), seed=0)
    bad = _episode(1, 4)
    bad["state"][2, 1] = np.nan
    with pytest.raises(DataError, match="NaN"):
        store.append_episode(bad)
    with pytest.raises(DataError, match="equally long"):
        store.append_episode({**_episode(1, 4), "action": np.zeros((3, 2), np.float32)})
    with pytest.raises(DataError, match="keys"):
        store.append_episode({"state": np.zeros((4, 5), np.float32)})
    again = EpisodeStore.open(tmp_path / "s.zarr")
    assert again.n_episodes == 1 and again.n_steps == 4


def test_episodes_appended_together_equal_those_appended_one_by_one_and_a_bad_one_refuses_them_all(tmp_path):
    one, many = (EpisodeStore.create(tmp_path / f"{n}.zarr", {"task": "pusht"}) for n in ("one", "many"))
    episodes = [_episode(i, n) for i, n in enumerate([3, 5, 2, 4])]
    for i, ep in enumerate(episodes):
        one.append_episode(ep, seed=7 + i, score=0.1 * i)
    many.append_episodes(episodes[:1], [7], [0.0])
    many.append_episodes(episodes[1:], [8, 9, 10], [0.1, 0.2, 0.30000000000000004])
    a, b = EpisodeStore.open(tmp_path / "one.zarr"), EpisodeStore.open(tmp_path / "many.zarr")
    np.testing.assert_array_equal(a.episode_ends, b.episode_ends)
    np.testing.assert_array_equal(a.episode_seeds(), b.episode_seeds())
    np.testing.assert_array_equal(a.episode_scores(), b.episode_scores())
    for key in a.keys:
        np.testing.assert_array_equal(a.read(key), b.read(key))
    bad = _episode(9, 3)
    bad["action"][1, 0] = np.inf
    with pytest.raises(DataError, match="NaN or inf"):
        many.append_episodes([_episode(8, 2), bad], [11, 12])
    assert EpisodeStore.open(tmp_path / "many.zarr").n_episodes == 4 and b.n_steps == 14


def test_create_never_replaces_what_is_there(tmp_path):
    """Replacing is the collector's business (staged beside, then renamed): a store is only ever created anew."""
    path = tmp_path / "s.zarr"
    EpisodeStore.create(path, {}).append_episode(_episode(0, 2))
    with pytest.raises(DataError, match="already exists"):
        EpisodeStore.create(path, {})
    assert EpisodeStore.open(path).n_episodes == 1


@pytest.mark.parametrize("make", ["missing", "file", "plain_dir", "no_ends", "short_data", "bad_ends"])
def test_open_rejects_what_is_not_a_valid_store(tmp_path, make):
    path = tmp_path / "s.zarr"
    if make == "file":
        path.write_text("hello")
    elif make == "plain_dir":
        path.mkdir()
    elif make != "missing":
        store = EpisodeStore.create(path, {})
        store.append_episode(_episode(0, 4))
        import zarr

        g = zarr.open_group(str(path), mode="r+")
        if make == "no_ends":
            del g["meta"]["episode_ends"]
        elif make == "short_data":
            g["data/state"].resize((2, 5))
        else:
            g["meta/episode_ends"].resize((2,))
            g["meta/episode_ends"][:] = [4, 3]
    with pytest.raises(DataError) as err:
        EpisodeStore.open(path)
    assert str(path) in str(err.value)


WRITER = textwrap.dedent(
    """
    import sys, numpy as np
    sys.path.insert(0, {root!r})
    from gpc.datasets.store import EpisodeStore
    store = EpisodeStore.create({path!r}, {{"task": "test"}})
    rng = np.random.default_rng(0)
    i = 0
    while True:
        n = int(rng.integers(1, 400))
        store.append_episode({{
            "state": np.full((n, 5), i, np.float32),
            "img": np.full((n, 32, 32, 3), i % 200, np.uint8),
        }}, seed=i)
        i += 1
        print(i, flush=True)
    """
)


@pytest.mark.parametrize("delay", [0.05, 0.3, 0.9, 1.7])
def test_sigkill_during_appends_leaves_only_whole_episodes(tmp_path, delay):
    path = str(tmp_path / "killed.zarr")
    proc = subprocess.Popen([sys.executable, "-c", WRITER.format(root=str(ROOT), path=path)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.time() + 30
    while not Path(path, "meta", "episode_ends", ".zarray").exists() and time.time() < deadline:
        time.sleep(0.01)  # start the clock once the store exists, so every delay kills mid-append
    time.sleep(delay)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    store = EpisodeStore.open(path)
    for i in range(store.n_episodes):
        ep = store.episode(i)
        assert np.all(ep["state"] == i) and np.all(ep["img"] == i % 200)
    np.testing.assert_array_equal(store.episode_seeds(), np.arange(store.n_episodes))
    # A writer reopening the store drops the half-written tail and appends cleanly.
    writer = EpisodeStore.open(path, writable=True)
    n = writer.n_episodes
    writer.append_episode({"state": np.full((3, 5), n, np.float32), "img": np.zeros((3, 32, 32, 3), np.uint8)}, seed=n)
    again = EpisodeStore.open(path)
    assert again.n_episodes == n + 1
    assert all(again.array(k).shape[0] == again.n_steps for k in again.keys)
    assert not list(Path(path).rglob("*.partial"))


def test_torn_commit_record_is_dropped(tmp_path):
    """The state a kill between zarr's resize and chunk write leaves: a trailing 0."""
    import zarr

    path = tmp_path / "s.zarr"
    store = EpisodeStore.create(path, {})
    store.append_episode(_episode(0, 3), seed=0)
    store.append_episode(_episode(1, 2), seed=1)
    g = zarr.open_group(str(path), mode="r+")
    g["data/state"].resize((9, 5))
    g["meta/episode_ends"].resize((3,))
    reader = EpisodeStore.open(path)
    assert reader.n_episodes == 2 and reader.n_steps == 5
    writer = EpisodeStore.open(path, writable=True)
    assert g["meta/episode_ends"].shape == (2,) and g["data/state"].shape == (5, 5)
    writer.append_episode(_episode(2, 4), seed=2)
    np.testing.assert_array_equal(EpisodeStore.open(path).episode_ends, [3, 5, 9])
