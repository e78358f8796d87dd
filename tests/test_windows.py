import numpy as np
import pytest
import torch

from gpc.datasets.datamodule import DataConfig, EpisodeDataModule
from gpc.datasets.errors import DataError
from gpc.datasets.normalizer import MinMaxNormalizer
from gpc.datasets.sequence import WindowSpec, split_episodes, window_indices, window_starts
from gpc.datasets.store import EpisodeStore


def test_windows_pad_like_diffusion_policy():
    ends = np.array([5, 8])
    spec = WindowSpec(horizon=4, pad_before=1, pad_after=2)
    rows = window_starts(ends, np.array([0, 1]), spec)
    # Episode 0 (length 5): offsets -1..3; episode 1 (length 3): offsets -1..1.
    assert len(rows) == 5 + 3
    np.testing.assert_array_equal(window_indices(rows[0], 4), [0, 0, 1, 2])
    np.testing.assert_array_equal(window_indices(rows[4], 4), [3, 4, 4, 4])
    np.testing.assert_array_equal(window_indices(rows[5], 4), [5, 5, 6, 7])
    np.testing.assert_array_equal(window_indices(rows[7], 4), [6, 7, 7, 7])
    with pytest.raises(DataError, match="horizon"):
        window_starts(np.array([2]), np.array([0]), WindowSpec(horizon=8))


def test_split_is_seeded_by_episode_and_disjoint():
    tr, va = split_episodes(50, 0.1, seed=1)
    tr2, va2 = split_episodes(50, 0.1, seed=1)
    np.testing.assert_array_equal(va, va2)
    assert len(va) == 5 and len(np.intersect1d(tr, va)) == 0 and len(tr) + len(va) == 50
    assert not np.array_equal(va, split_episodes(50, 0.1, seed=2)[1])


def test_normalizer_maps_to_unit_range_and_survives_state_dict():
    data = {"a": np.random.default_rng(0).uniform(-3, 7, (200, 9, 2)), "c": np.ones((10, 2))}
    norm = MinMaxNormalizer.fit(data)
    x = torch.as_tensor(data["a"], dtype=torch.float32)
    y = norm.normalize("a", x)
    assert y.min() >= -1 - 1e-6 and y.max() <= 1 + 1e-6 and y.min() < -0.99
    fresh = MinMaxNormalizer()
    fresh.load_state_dict(norm.state_dict())
    torch.testing.assert_close(fresh.unnormalize("a", y), x, atol=1e-4, rtol=0)
    assert torch.all(fresh.normalize("c", torch.ones(3, 2)) == 0)  # a constant feature maps to 0


def test_datamodule_on_a_store(tmp_path):
    path = tmp_path / "s.zarr"
    store = EpisodeStore.create(path, {"task": "t"})
    for i in range(10):
        n = 20 + i
        store.append_episode({"state": np.arange(n * 5, dtype=np.float32).reshape(n, 5) + i,
                              "action": np.full((n, 2), i, np.float32)}, seed=i)
    dm = EpisodeDataModule(DataConfig(paths=(str(path),), batch_size=4, val_ratio=0.2))
    batch = next(iter(dm.train_dataloader()))
    assert batch["state"].shape == (4, 2, 5) and batch["action"].shape == (4, 16, 2)
    assert len(dm.val_episodes) == 2
    # Within a window the action is constant: windows never cross an episode boundary.
    assert torch.all(batch["action"] == batch["action"][:, :1])
    with pytest.raises(DataError, match="longer than every episode"):
        EpisodeDataModule(DataConfig(paths=(str(path),), horizon=64, n_obs_steps=2, n_action_steps=8))
    with pytest.raises(DataError, match="missing key data/img"):
        EpisodeDataModule(DataConfig(paths=(str(path),), obs_keys=("img",)))


def test_a_declared_span_widens_only_its_feature_and_a_bad_span_is_refused():
    from gpc.datasets.layout import StateLayout

    data = {"state": np.array([[0.0, 10.0, 0.001], [2.0, 30.0, 0.003]])}
    norm = MinMaxNormalizer.fit(data, spans={"state": ((2, 0.0, 1.0),)})
    y = norm.normalize("state", torch.tensor([[1.0, 20.0, 0.5]]))
    torch.testing.assert_close(y, torch.tensor([[0.0, 0.0, 0.0]]))  # entries 0, 1 fitted to the data; 2 to [0, 1]
    wide = MinMaxNormalizer.fit(data, spans={"state": ((0, 0.5, 1.0),)})  # a span inside the data's range narrows nothing
    torch.testing.assert_close(wide.normalize("state", torch.tensor([[2.0, 10.0, 0.003]])), torch.tensor([[1.0, -1.0, 1.0]]))
    with pytest.raises(ValueError, match="spans"):
        StateLayout(dim=3, spans=((3, 0.0, 1.0),))
    with pytest.raises(ValueError, match="span of state entry 1"):
        StateLayout(dim=3, spans=((1, 1.0, 1.0),))
