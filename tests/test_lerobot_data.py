"""LeRobot datasets as training data: `gpc data import` / `gpc data export`, with real files on disk.

The round trip (our store -> LeRobot v3.0 -> our store) must be identical, frames included
(lossless H.264). Datasets in LeRobot's own layouts (v3.0 as the hub's converted datasets
hold them, with ``list<float>`` columns and PNG images; v2.1 with one parquet and one MP4 per
episode) are written here by the test itself with pyarrow and PyAV, as LeRobot lays them out
(``/work/notes``-style facts are in ``docs/data.md``), and read back through Push-T's mapping.
"""

from __future__ import annotations

import json
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from gpc.cli.main import app
from gpc.datasets.store import EpisodeStore
from gpc.harness.collection import CollectJob, collect
from gpc.tasks.pusht import geometry

pa = pytest.importorskip("pyarrow", reason="LeRobot datasets need pyarrow (a dependency of gpc)")
pq = pytest.importorskip("pyarrow.parquet")
av = pytest.importorskip("av", reason="LeRobot videos need PyAV (a dependency of gpc)")
pytestmark = pytest.mark.usefixtures("one_thread")
cli = CliRunner()


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("lr") / "expert.zarr"
    collect(CollectJob(task="pusht", out=path, episodes=2, images=True, max_steps=25))
    return path


def _same_store(a: Path, b: Path) -> None:
    x, y = EpisodeStore.open(a), EpisodeStore.open(b)
    assert x.keys == y.keys and np.array_equal(x.episode_ends, y.episode_ends)
    for key in x.keys:
        assert x.read(key).dtype == y.read(key).dtype and np.array_equal(x.read(key), y.read(key)), key
    assert np.array_equal(x.episode_seeds(), y.episode_seeds()) and np.array_equal(x.episode_scores(), y.episode_scores())


def test_round_trip_store_to_lerobot_and_back_is_identical(store, tmp_path):
    result = cli.invoke(app, ["data", "export", str(store), "--out", str(tmp_path / "lr")])
    assert result.exit_code == 0, result.output
    info = json.loads((tmp_path / "lr" / "meta" / "info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["fps"] == 10 and info["total_episodes"] == 2
    assert info["features"]["observation.environment_state"]["shape"] == [16]
    assert info["features"]["observation.image"]["dtype"] == "video"
    schema = pq.read_schema(tmp_path / "lr" / "data" / "chunk-000" / "file-000.parquet")
    assert pa.types.is_fixed_size_list(schema.field("observation.state").type)
    back = cli.invoke(app, ["data", "import", str(tmp_path / "lr"), "--out", str(tmp_path / "back.zarr")])
    assert back.exit_code == 0 and "exactly" in back.output, back.output
    _same_store(store, tmp_path / "back.zarr")


def test_h264_export_keeps_vectors_exact_and_frames_close(store, tmp_path):
    assert cli.invoke(app, ["data", "export", str(store), "--out", str(tmp_path / "lr"), "--video", "h264"]).exit_code == 0
    assert cli.invoke(app, ["data", "import", str(tmp_path / "lr"), "--out", str(tmp_path / "back.zarr")]).exit_code == 0
    a, b = EpisodeStore.open(store), EpisodeStore.open(tmp_path / "back.zarr")
    assert np.array_equal(a.read("state"), b.read("state"))
    diff = np.abs(a.read("img").astype(int) - b.read("img").astype(int))
    assert diff.mean() < 3.0 and np.percentile(diff, 99) < 40  # yuv420p chroma at the T's edges


def _poses(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    agent = rng.uniform(50, 450, (n, 2))
    pose = np.column_stack([rng.uniform(150, 350, n), rng.uniform(150, 350, n), rng.uniform(-3.0, 3.0, n)])
    return agent.astype(np.float32), pose


def _frames(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = np.linspace(0, 255, 96, dtype=np.float64)[None, :, None] * np.ones((96, 96, 3))
    return np.stack([np.clip(base + rng.integers(0, 40), 0, 255).astype(np.uint8) for _ in range(n)])


def _mp4(path: Path, frames: np.ndarray, start: int = 0) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), "w") as c:
        s = c.add_stream("libx264rgb", rate=10, options={"qp": "0", "g": "2"})
        s.width = s.height = 96
        s.pix_fmt, s.time_base = "rgb24", Fraction(1, 10)
        for i, im in enumerate(frames):
            f = av.VideoFrame.from_ndarray(im, format="rgb24")
            f.pts = start + i
            for p in s.encode(f):
                c.mux(p)
        for p in s.encode():
            c.mux(p)


def _write_v21(root: Path, lengths: list[int]) -> dict:
    """LeRobot 0.3's layout: one parquet and one MP4 per episode, episodes.jsonl, tasks.jsonl, ``fixed_size_list``."""
    want = {"state": [], "img": []}
    (root / "meta").mkdir(parents=True)
    start = 0
    for e, n in enumerate(lengths):
        agent, pose = _poses(n, e)
        frames = _frames(n, e)
        verts = geometry.outline_vertices(pose).reshape(n, 16).astype(np.float32)
        cols = {"observation.state": pa.FixedSizeListArray.from_arrays(pa.array(agent.reshape(-1)), 2),
                "observation.environment_state": pa.FixedSizeListArray.from_arrays(pa.array(verts.reshape(-1)), 16),
                "action": pa.FixedSizeListArray.from_arrays(pa.array(agent.reshape(-1) + 1), 2),
                "timestamp": pa.array((np.arange(n) / 10).astype(np.float32)), "frame_index": pa.array(np.arange(n)),
                "episode_index": pa.array(np.full(n, e)), "index": pa.array(np.arange(start, start + n)),
                "task_index": pa.array(np.zeros(n, np.int64))}
        path = root / "data" / "chunk-000" / f"episode_{e:06d}.parquet"
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.table(cols), path)
        _mp4(root / "videos" / "chunk-000" / "observation.image" / f"episode_{e:06d}.mp4", frames)
        want["state"].append(np.column_stack([agent, pose]))
        want["img"].append(frames)
        start += n
    (root / "meta" / "episodes.jsonl").write_text("".join(
        json.dumps({"episode_index": e, "tasks": ["push"], "length": n}) + "\n" for e, n in enumerate(lengths)))
    (root / "meta" / "tasks.jsonl").write_text(json.dumps({"task_index": 0, "task": "push"}) + "\n")
    feats = {"observation.state": {"dtype": "float32", "shape": [2]}, "observation.environment_state": {"dtype": "float32", "shape": [16]},
             "action": {"dtype": "float32", "shape": [2]},
             "observation.image": {"dtype": "video", "shape": [96, 96, 3], "names": ["height", "width", "channel"]},
             **{k: {"dtype": "int64", "shape": [1]} for k in ("frame_index", "episode_index", "index", "task_index")},
             "timestamp": {"dtype": "float32", "shape": [1]}}
    (root / "meta" / "info.json").write_text(json.dumps({
        "codebase_version": "v2.1", "fps": 10, "total_episodes": len(lengths), "chunks_size": 1000,
        "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet",
        "video_path": "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4", "features": feats}))
    return {k: np.concatenate(v) for k, v in want.items()}


def _write_v30_converted(root: Path, lengths: list[int]) -> dict:
    """The hub's converted v3.0 layout: all episodes in one parquet, ``list<float>`` vectors, PNG images."""
    import cv2

    agent, pose = _poses(sum(lengths), 7)
    frames = _frames(sum(lengths), 7)
    n = sum(lengths)
    verts = geometry.outline_vertices(pose).reshape(n, 16).astype(np.float32)
    pngs = [cv2.imencode(".png", cv2.cvtColor(f, cv2.COLOR_RGB2BGR))[1].tobytes() for f in frames]
    episode = np.repeat(np.arange(len(lengths)), lengths)
    frame_index = np.concatenate([np.arange(k) for k in lengths])
    cols = {"observation.state": pa.array(agent.tolist(), pa.list_(pa.float32())),
            "observation.environment_state": pa.array(verts.tolist(), pa.list_(pa.float32())),
            "action": pa.array(agent.tolist(), pa.list_(pa.float32())),
            "observation.image": pa.StructArray.from_arrays([pa.array(pngs, pa.binary()), pa.array([None] * n, pa.string())],
                                                            names=["bytes", "path"]),
            "timestamp": pa.array((frame_index / 10).astype(np.float32)), "frame_index": pa.array(frame_index),
            "episode_index": pa.array(episode), "index": pa.array(np.arange(n)), "task_index": pa.array(np.zeros(n, np.int64))}
    (root / "data" / "chunk-000").mkdir(parents=True)
    order = np.random.default_rng(0).permutation(n)  # rows out of order: the reader sorts by frame_index
    pq.write_table(pa.table(cols).take(pa.array(order)), root / "data" / "chunk-000" / "file-000.parquet")
    ends = np.cumsum(lengths)
    (root / "meta" / "episodes" / "chunk-000").mkdir(parents=True)
    pq.write_table(pa.table({"episode_index": pa.array(np.arange(len(lengths))), "length": pa.array(lengths),
                             "data/chunk_index": pa.array([0] * len(lengths)), "data/file_index": pa.array([0] * len(lengths)),
                             "dataset_from_index": pa.array(ends - lengths), "dataset_to_index": pa.array(ends)}),
                   root / "meta" / "episodes" / "chunk-000" / "file-000.parquet")
    feats = {"observation.state": {"dtype": "float32", "shape": [2], "fps": 10},
             "observation.environment_state": {"dtype": "float32", "shape": [16], "fps": 10},
             "action": {"dtype": "float32", "shape": [2], "fps": 10},
             "observation.image": {"dtype": "image", "shape": [3, 96, 96], "names": ["channel", "height", "width"]}}
    (root / "meta" / "info.json").write_text(json.dumps({
        "codebase_version": "v3.0", "fps": 10, "total_episodes": len(lengths),
        "data_path": "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet", "video_path": None, "features": feats}))
    return {"state": np.column_stack([agent, pose]), "img": frames}


@pytest.mark.parametrize("layout", ["v2.1-videos", "v3.0-converted-png"])
def test_lerobot_layouts_import_through_pushts_mapping(tmp_path, layout):
    root = tmp_path / "lr"
    want = (_write_v21 if layout.startswith("v2.1") else _write_v30_converted)(root, [6, 9])
    result = cli.invoke(app, ["data", "import", str(root), "--out", str(tmp_path / "s.zarr")])
    assert result.exit_code == 0 and "mapped by task pusht" in result.output, result.output
    got = EpisodeStore.open(tmp_path / "s.zarr")
    assert got.n_episodes == 2 and list(got.episode_ends) == [6, 15]
    state = got.read("state")
    assert np.allclose(state[:, :4], want["state"][:, :4], atol=1e-3)
    turn = (state[:, 4] - want["state"][:, 4] + np.pi) % (2 * np.pi) - np.pi
    assert np.abs(turn).max() < 1e-5
    assert np.allclose(got.read("keypoint"), geometry.block_keypoints(want["state"][:, 2:5]), atol=1e-2)
    assert np.array_equal(got.read("img"), want["img"])  # lossless video / PNG
    assert got.attrs["imported_from"]["codebase_version"] in ("v2.1", "v3.0")


def test_an_imported_store_trains_a_policy(store, tmp_path):
    assert cli.invoke(app, ["data", "export", str(store), "--out", str(tmp_path / "lr"), "--video", "h264"]).exit_code == 0
    (tmp_path / "lr" / "meta" / "gpc.json").unlink()  # as if LeRobot had written it: Push-T's mapping rebuilds the state
    assert cli.invoke(app, ["data", "import", str(tmp_path / "lr"), "--out", str(tmp_path / "s.zarr")]).exit_code == 0
    result = cli.invoke(app, ["train", "policy", "--dataset", str(tmp_path / "s.zarr"), "--obs", "keypoints", "--profile", "tiny",
                              "--max-steps", "2", "--batch-size", "8", "--accelerator", "cpu", "--out", str(tmp_path / "p"),
                              "--no-progress"])
    assert result.exit_code == 0, result.output
    a, b = EpisodeStore.open(store).read("state"), EpisodeStore.open(tmp_path / "s.zarr").read("state")
    assert np.allclose(a[:, :4], b[:, :4], atol=1e-3)


def test_training_on_a_lerobot_directory_says_how_to_convert_it(tmp_path):
    _write_v21(tmp_path / "lr", [4, 5])
    result = cli.invoke(app, ["train", "policy", "--dataset", str(tmp_path / "lr"), "--profile", "tiny", "--out", str(tmp_path / "p")])
    assert result.exit_code == 2 and "a LeRobot dataset, not a Zarr episode store" in result.output
    assert "gpc data import" in result.output and not (tmp_path / "p").exists()


@pytest.mark.parametrize("case,expect", [
    ("no-info", "not a LeRobot dataset (no meta/info.json)"),
    ("old-version", "codebase_version 'v1.6': gpc reads v2.0, v2.1 and v3.0"),
    ("missing-video", "episode_000001.mp4: missing (episode 1's observation.image video)"),
    ("no-env-state", "Push-T needs observation.environment_state to rebuild its state"),
    ("out-exists", "already exists; gpc converts only into a new path"),
])
def test_bad_datasets_are_one_line_exit_2(tmp_path, case, expect):
    root = tmp_path / "lr"
    _write_v21(root, [4, 5])
    out = tmp_path / "s.zarr"
    info = json.loads((root / "meta" / "info.json").read_text())
    if case == "no-info":
        (root / "meta" / "info.json").unlink()
    elif case == "old-version":
        (root / "meta" / "info.json").write_text(json.dumps({**info, "codebase_version": "v1.6"}))
    elif case == "missing-video":
        (root / "videos" / "chunk-000" / "observation.image" / "episode_000001.mp4").unlink()
    elif case == "no-env-state":
        info["features"].pop("observation.environment_state")
        (root / "meta" / "info.json").write_text(json.dumps(info))
    elif case == "out-exists":
        out.mkdir()
        (out / "mine.txt").write_text("keep")
    result = cli.invoke(app, ["data", "import", str(root), "--out", str(out)])
    assert result.exit_code == 2 and expect in result.output, result.output
    assert len(result.output.strip().splitlines()) == 1 and "Traceback" not in result.output
    assert (out / "mine.txt").read_text() == "keep" if case == "out-exists" else not out.exists()
    assert not (tmp_path / ".s.zarr.partial").exists()


def test_export_without_images_leaves_the_frames_out(store, tmp_path):
    assert cli.invoke(app, ["data", "export", str(store), "--out", str(tmp_path / "lr"), "--no-images"]).exit_code == 0
    info = json.loads((tmp_path / "lr" / "meta" / "info.json").read_text())
    assert "observation.image" not in info["features"] and info["video_path"] is None
    assert not (tmp_path / "lr" / "videos").exists()
    assert cli.invoke(app, ["data", "import", str(tmp_path / "lr"), "--out", str(tmp_path / "s.zarr")]).exit_code == 0
    got = EpisodeStore.open(tmp_path / "s.zarr")
    assert "img" not in got.keys and np.array_equal(got.read("state"), EpisodeStore.open(store).read("state"))


def test_export_refuses_a_task_the_store_is_not_of(tmp_path):
    """A swap store exported as Push-T would read the cube's pose as the T's: refused in one line, nothing written."""
    collect(CollectJob(task="swap", out=tmp_path / "swap.zarr", episodes=1, images=False, max_steps=10))
    result = cli.invoke(app, ["data", "export", str(tmp_path / "swap.zarr"), "--out", str(tmp_path / "lr"), "--task", "pusht"])
    assert result.exit_code == 2 and "a store of task swap, not of task pusht (--task)" in result.output, result.output
    assert len(result.output.strip().splitlines()) == 1 and not (tmp_path / "lr").exists()


@pytest.mark.parametrize("damage,expect", [
    ("[]", "not gpc's record of an export"),
    ("seeds", "episode_seeds: want a list of 2"),
    ("dtype", "keys.state: want a shape of sizes and a numpy dtype"),
])
def test_a_damaged_export_record_is_one_line(store, tmp_path, damage, expect):
    assert cli.invoke(app, ["data", "export", str(store), "--out", str(tmp_path / "lr"), "--no-images"]).exit_code == 0
    meta = tmp_path / "lr" / "meta" / "gpc.json"
    record = json.loads(meta.read_text())
    if damage == "seeds":
        record["gpc"]["episode_seeds"] = record["gpc"]["episode_seeds"][:1]
    elif damage == "dtype":
        record["gpc"]["keys"]["state"]["dtype"] = "float99"
    meta.write_text("[]" if damage == "[]" else json.dumps(record))
    result = cli.invoke(app, ["data", "import", str(tmp_path / "lr"), "--out", str(tmp_path / "s.zarr")])
    assert result.exit_code == 2 and expect in result.output and len(result.output.strip().splitlines()) == 1, result.output
    assert not (tmp_path / "s.zarr").exists()
