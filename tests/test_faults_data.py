"""Missing or damaged data is an error, never a value: every reader refuses it in one line naming the store, the
array and the chunk or step (zarr would read a lost chunk as zeros), before anything is written."""

from __future__ import annotations

import shutil
from pathlib import Path

import numcodecs
import numpy as np
import pytest
import zarr
from faults import digest, gpc, inline, one_line, string_store

from gpc.datasets.store import EpisodeStore

pytestmark = pytest.mark.usefixtures("one_thread")

COLLECT = ["--no-images", "--max-steps", "40"]


@pytest.fixture(scope="module")
def collected(tmp_path_factory) -> Path:
    """Three expert episodes as `gpc collect` writes them (a resume adds a fourth)."""
    path = tmp_path_factory.mktemp("data") / "s.zarr"
    assert inline("collect", "--out", str(path), "--episodes", "3", *COLLECT)[0] == 0
    return path


def _copy(src: Path, tmp: Path) -> Path:
    dst = tmp / "copy.zarr"
    shutil.copytree(src, dst)
    return dst


def _truncate(chunk: Path) -> None:
    chunk.write_bytes(chunk.read_bytes()[: chunk.stat().st_size // 2])


def _readers(store: Path, tmp: Path) -> dict[str, list[str]]:
    """Every command that reads a store, and where it would write."""
    return {
        "info": ["data", "info", str(store)],
        "train": ["train", "policy", "--dataset", str(store), "--out", str(tmp / "run"), "--profile", "tiny", "--max-steps", "2",
                  "--accelerator", "cpu", "--no-progress"],
        "collect resume": ["collect", "--out", str(store), "--episodes", "4", *COLLECT],
        "export": ["data", "export", str(store), "--out", str(tmp / "lerobot"), "--no-images"],
    }


def _refused(args: list[str], store: Path, tmp: Path, *fragments: str, process: bool = False) -> None:
    """Exit 2, one line naming the store and the fragments, every byte of the store kept and nothing else written."""
    before = digest(store)
    one_line(gpc(*args) if process else inline(*args), 2, str(store), *fragments)
    assert digest(store) == before
    assert not (tmp / "run").exists() and not (tmp / "lerobot").exists()


@pytest.mark.parametrize("reader", ["info", "train", "collect resume", "export"])
def test_a_deleted_chunk_is_refused_by_every_reader_not_read_as_zeros(collected, tmp_path, reader):
    store = _copy(collected, tmp_path)
    (store / "data" / "state" / "0.0").unlink()
    _refused(_readers(store, tmp_path)[reader], store, tmp_path, "data/state chunk 0 (steps 0-119) is missing",
             process=reader == "info")


@pytest.mark.parametrize("chunk", ["meta/episode_ends/0", "meta/episode_seeds/0", "data/n_contacts/0.0"])
def test_a_deleted_chunk_of_any_array_is_named(collected, tmp_path, chunk):
    store = _copy(collected, tmp_path)
    (store / chunk).unlink()
    array = chunk.rsplit("/", 1)[0]
    _refused(_readers(store, tmp_path)["info"], store, tmp_path, f"{array} chunk 0", f"no file {chunk}")


def test_overwrite_still_replaces_a_damaged_store_gpc_wrote(collected, tmp_path):
    """Whose store it is does not hang on its data: the way out of a lost chunk is to collect the store again."""
    store = _copy(collected, tmp_path)
    (store / "data" / "state" / "0.0").unlink()
    assert inline("collect", "--out", str(store), "--episodes", "3", *COLLECT, "--overwrite")[0] == 0
    np.testing.assert_array_equal(EpisodeStore.open(store).read("state"), EpisodeStore.open(collected).read("state"))


def test_a_store_of_format_1_missing_a_chunk_says_it_may_be_one_of_zeros(collected, tmp_path):
    """gpc before format 2 let zarr skip chunks of zeros (as zarr 3 does by default for any writer): such a store is
    refused all the same, saying what the absent chunk may be."""
    store = _copy(collected, tmp_path)
    zarr.open_group(str(store), mode="r+").attrs["gpc_format"] = 1
    (store / "data" / "n_contacts" / "0.0").unlink()
    _refused(_readers(store, tmp_path)["info"], store, tmp_path, "data/n_contacts chunk 0", "skips chunks of zeros")


def test_chunks_of_zeros_are_written_so_an_absent_chunk_is_a_lost_one(tmp_path):
    """zarr 3 skips writing a chunk that is all fill value; gpc's writer does not (a seed 0, a score 0, no contacts)."""
    path = tmp_path / "zeros.zarr"
    EpisodeStore.create(path, {}).append_episode({"n_contacts": np.zeros((5, 1), np.float32)}, seed=0, score=0.0)
    for chunk in ("data/n_contacts/0.0", "meta/episode_ends/0", "meta/episode_seeds/0", "meta/episode_scores/0"):
        assert (path / chunk).is_file(), chunk
    np.testing.assert_array_equal(EpisodeStore.open(path).episode_seeds(), [0])


def test_resuming_into_a_truncated_chunk_changes_no_byte(collected, tmp_path):
    """Was: exit 1, a 104-line traceback, and data/state/.zarray grown by the new episode's rows."""
    store = _copy(collected, tmp_path)
    _truncate(store / "data" / "state" / "0.0")
    _refused(_readers(store, tmp_path)["collect resume"], store, tmp_path, "data/state chunk 0 (steps 0-119) is damaged",
             "data/state/0.0 has")


def test_an_undecodable_chunk_of_a_many_chunk_array_is_one_line(tmp_path):
    """A failed read leaves zarr's other chunk reads running: without waiting for them, about 150 lines of
    'Exception ignored ... Event loop is closed' followed gpc's line at exit (a real process: it is the exit)."""
    path = tmp_path / "many.zarr"
    root = zarr.open_group(str(path), mode="w", zarr_format=2)
    n = 20000  # 2000 chunks of 10 steps
    root.create_group("data")
    for key, width in (("state", 5), ("action", 2)):
        root.create_array(f"data/{key}", data=np.linspace(0, 512, n * width, dtype=np.float32).reshape(n, width), chunks=(10, width),
                          compressors=numcodecs.Zstd())  # not blosc: its size is not in a header, so the decoder fails
    root.create_group("meta").create_array("episode_ends", data=np.arange(100, n + 1, 100, dtype=np.int64))
    _truncate(path / "data" / "state" / "1.0")
    _refused(["data", "info", str(path)], path, tmp_path, "data/state chunk 1 (steps 10-19) cannot be decoded", process=True)


def test_resuming_a_store_that_holds_nan_is_refused_before_appending(collected, tmp_path):
    store = _copy(collected, tmp_path)
    zarr.open_group(str(store), mode="r+")["data/action"][57, 1] = np.nan
    _refused(_readers(store, tmp_path)["collect resume"], store, tmp_path, "data/action holds NaN or inf (first at step 57)")


def test_exporting_a_store_of_strings_is_refused(tmp_path):
    store = string_store(tmp_path / "s.zarr")
    _refused(_readers(store, tmp_path)["export"], store, tmp_path, "data/state holds <U1 values, not numbers")


def test_a_two_dimensional_episode_ends_is_named_with_its_shape(tmp_path):
    """Was: "The truth value of an array ... is ambiguous", naming no file or key."""
    store = string_store(tmp_path / "s.zarr")
    shutil.rmtree(store / "meta" / "episode_ends")
    zarr.open_group(str(store), mode="r+").create_array("meta/episode_ends", data=np.array([[10], [20]], np.int64))
    _refused(_readers(store, tmp_path)["info"], store, tmp_path, "meta/episode_ends has shape (2, 1)")


def test_importing_a_dataset_that_holds_nan_names_the_dataset_and_episode(collected, tmp_path):
    """The import's own check (a LeRobot dataset is no store): refused naming the dataset, not its removed staging copy."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    dataset, out = tmp_path / "lerobot", tmp_path / "back.zarr"
    assert inline("data", "export", str(collected), "--out", str(dataset), "--no-images")[0] == 0
    table_file = next((dataset / "data").rglob("*.parquet"))
    table = pq.read_table(table_file)
    state = np.asarray(table.column("gpc.state").to_pylist(), np.float32)
    state[45, 2] = np.nan  # episode 1 (its steps are 40-79)
    column = pa.array(list(state), type=table.schema.field("gpc.state").type)
    pq.write_table(table.set_column(table.column_names.index("gpc.state"), "gpc.state", column), table_file)
    before = digest(dataset)
    one_line(inline("data", "import", str(dataset), "--out", str(out)), 2, f"{dataset}: episode 1", "NaN or inf into data/state")
    assert digest(dataset) == before and not out.exists() and not (tmp_path / ".back.zarr.partial").exists()
