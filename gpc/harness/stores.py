"""What a store holds, for `gpc data info` and `gpc data video`: keys, episodes, scores, coverage, an MP4."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from gpc.datasets.errors import DataError
from gpc.datasets.store import EpisodeStore, store_record
from gpc.harness.files import check_file_out
from gpc.harness.video import write_mp4
from gpc.tasks import DEFAULT_TASK, get_task
from gpc.tasks.base import GOAL_KEY, IMAGE_KEY, Task


def task_of(store: EpisodeStore) -> str:
    """Our stores name their task; a store without that record (Diffusion Policy's) is taken as the default task's."""
    return str(store.attrs.get("task", DEFAULT_TASK if "state" in store.keys else ""))


def describe_store(path: Path) -> dict[str, Any]:
    """Episodes, steps, keys and shapes, episode lengths, contact fraction, scores and pose coverage."""
    store = EpisodeStore.open(path)
    store.verify([k for k in store.keys if k != "img"])
    lengths = np.diff(np.concatenate([[0], store.episode_ends]))
    info: dict = {
        "path": str(path), "episodes": store.n_episodes, "steps": store.n_steps,
        "keys": {k: {"shape": list(store.shape(k)), "dtype": str(store.array(k).dtype)} for k in store.keys},
        "episode_length": _stats(lengths) if store.n_episodes else {},
        "attrs": store.attrs,
    }
    task_name = task_of(store)
    if task_name:
        try:  # the task's figures only for a store laid out as the task's
            check_stores(get_task(task_name), [path], [k for k in ("state", "action", "n_contacts") if k in store.keys])
        except (DataError, ValueError) as exc:
            info["task_note"] = f"no task figures: {exc}"
            task_name = ""
    if "n_contacts" in store.keys and store.n_steps and task_name:
        info["contact_fraction"] = float((store.read("n_contacts")[:, 0] > 0).mean())
    scores = store.episode_scores()
    if (scores is None or not np.all(np.isfinite(scores))) and task_name and "state" in store.keys and store.n_episodes:
        arrays = {key: store.read(key) for key in ("state", GOAL_KEY) if key in store.keys}
        try:
            scores = get_task(task_name).episode_scores(arrays, store.episode_ends)
        except DataError as exc:  # a store the task cannot score (swap's replays hold no goals): described without
            info["score_note"] = f"no scores: {exc}"
            scores = None
    if scores is not None and store.n_episodes:
        succeeded = get_task(task_name).succeeded if task_name else None
        info["score"] = _stats(scores) | ({} if succeeded is None else {"success_rate": float(np.mean(succeeded(scores)))})
    coverage = get_task(task_name).pose_coverage if task_name else None
    if coverage is not None and "state" in store.keys and store.n_steps:
        info["pose_coverage"] = float(coverage(store.read("state")))
    return info


def _stats(values: np.ndarray) -> dict[str, float]:
    v = np.asarray(values, dtype=np.float64)
    return {"mean": float(v.mean()), "min": float(v.min()), "p50": float(np.median(v)), "max": float(v.max())}


def episode_video(path: Path, episode: int, out: Path | None) -> Path:
    """One episode as an MP4: its recorded frames, or its states drawn by the task."""
    out = out or path.with_name(f"{path.name.removesuffix('.zarr')}_ep{episode}.mp4")
    check_file_out(out, ".mp4")
    store = EpisodeStore.open(path)
    ep = store.episode(episode, [k for k in ("img", "state", GOAL_KEY) if k in store.keys] or None)
    if "img" in ep:
        frames = np.clip(np.rint(ep["img"]), 0, 255).astype(np.uint8)
        write_mp4(frames, out, scale=4)
    elif "state" in ep and task_of(store):
        task = get_task(task_of(store))
        goals = ep.get(GOAL_KEY, [None] * len(ep["state"]))  # a goal drawn per episode is drawn with it
        write_mp4((task.render_state(s, g, size=384) for s, g in zip(ep["state"], goals)), out)
    else:
        raise DataError(f"{path}: episode {episode} has neither img nor state to draw")
    return out


def check_stores(task: Task, paths: Sequence[str | Path], keys: Sequence[str]) -> None:
    """Refuse, in one line naming the store and key, stores a component of ``task`` cannot train on: a missing
    key, values that are not numbers, or a step shape other than the task's (images: any square RGB size)."""
    if not paths:
        raise DataError("no dataset given (pass --dataset PATH)")
    for path in paths:
        store = EpisodeStore.open(path)
        recorded = task_of(store)
        if recorded and recorded != task.name:
            raise DataError(f"{path}: holds episodes of task {recorded}, not of task {task.name} (pass --task {recorded}, "
                            "or a store of this task)")
        if store.n_episodes == 0:
            raise DataError(f"{path}: holds no episodes")
        for key in keys:
            arr = store.array(key)
            if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == np.bool_):
                raise DataError(f"{path}: data/{key} holds {arr.dtype} values, not numbers")
            row, want = tuple(arr.shape[1:]), task.row_shape(key)
            if key == IMAGE_KEY and (len(row) != 3 or row[0] != row[1] or row[2] != 3):
                raise DataError(f"{path}: data/{key} frames are {row}, not square RGB (S, S, 3)")
            if want is not None and row != want:
                raise DataError(f"{path}: data/{key} rows are {row}; task {task.name} stores {want}")


_ZARR_META = frozenset({".zgroup", ".zattrs", ".zarray", ".zmetadata", "zarr.json"})
_META_ARRAYS = frozenset({"episode_ends", "episode_seeds", "episode_scores"})


def foreign_files(store: Path) -> list[Path]:
    """The files in a store gpc wrote that are not the Zarr layout gpc writes there (its metadata, the arrays
    its provenance records under ``data/`` and ``meta/``, their chunks): a user's, which ``--overwrite`` would
    delete with the store. Folders are judged by the files in them."""
    keys = store_record(store).get("keys")  # its data may be damaged: --overwrite replaces a damaged store of gpc's
    arrays = {"data": set(keys) if isinstance(keys, list) else None, "meta": _META_ARRAYS}
    foreign = []
    for path in sorted(store.rglob("*")):
        if path.is_dir() and not path.is_symlink():
            continue
        parts = path.relative_to(store).parts
        if len(parts) <= 2:
            ours = parts[-1] in _ZARR_META and (len(parts) == 1 or parts[0] in arrays)
        else:
            known = arrays.get(parts[0], set())
            ours = (parts[0] in arrays and (known is None or parts[1] in known)
                    and ((len(parts) == 3 and parts[2] in _ZARR_META) or _chunk_name(parts[2:])))
        if not ours:
            foreign.append(path)
    return foreign


def _chunk_name(parts: tuple[str, ...]) -> bool:
    """A Zarr chunk's key below its array: ``0.0`` (format 2), ``0/0`` or ``c/0/0`` (format 3), or the
    ``.partial`` file of a chunk being written."""
    words = [w for part in parts for w in part.removesuffix(".partial").split(".")]
    return all(w.isdigit() for w in words[parts[0] == "c":]) and len(words) > (parts[0] == "c")
