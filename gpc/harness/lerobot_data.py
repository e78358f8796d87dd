"""LeRobot datasets <-> gpc episode stores: ``gpc data import`` and ``gpc data export``.

Export writes each episode under the task's LeRobot feature names (Push-T: gym-pusht's state,
environment state, image and action, so LeRobot trains on it as on ``lerobot/pusht_keypoints``)
and also every store key verbatim as ``gpc.<key>``, with the store's record in
``meta/gpc.json``; import then restores the store exactly (lossless video: the frames too).
A dataset LeRobot wrote is imported through the task's ``from_lerobot`` (Push-T rebuilds its
state from the outline vertices). Both write beside the target and rename at the end, so a
failed or stopped conversion leaves nothing half written.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from gpc.datasets.errors import DataError
from gpc.datasets.lerobot import LeRobotReader, is_lerobot_dataset, write_lerobot
from gpc.datasets.store import EpisodeStore
from gpc.harness import interrupts
from gpc.harness.stores import task_of
from gpc.tasks import DEFAULT_TASK, get_task
from gpc.tasks.base import IMAGE_KEY, Task

VERBATIM = "gpc."  # prefix of the store keys an export keeps as they are
META = "gpc.json"


def _lerobot_task(task: Task) -> Task:
    if task.to_lerobot is None or task.from_lerobot is None:
        raise ValueError(f"task {task.name} has no LeRobot feature mapping (Task.to_lerobot / from_lerobot)")
    return task


def _check_new(out: Path) -> None:
    if out.exists() or out.is_symlink():
        raise DataError(f"{out}: already exists; gpc converts only into a new path (remove it or choose another)")
    if not out.parent.exists():
        raise DataError(f"{out.parent}: no such directory")


@contextmanager
def _staged(out: Path) -> Iterator[Path]:
    """Where the conversion is written (a new folder of a name nobody else uses, beside ``out``), renamed to
    ``out`` when the block ends; a failure or a stop removes it, and only it."""
    try:
        place = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".partial", dir=out.parent))
    except OSError as exc:
        raise DataError(f"{out}: cannot be written ({exc.strerror or exc})") from None
    try:
        yield place / out.name
        interrupts.check()
        os.rename(place / out.name, out)
    finally:
        shutil.rmtree(place, ignore_errors=True)


def export_store(store_path: Path, out: Path, video: str = "lossless", task: str | None = None,
                 images: bool = True) -> dict[str, Any]:
    """A gpc store as a LeRobot v3.0 dataset in ``out`` (a new directory); ``images=False`` leaves the frames out
    (a keypoint policy trains faster without LeRobot decoding a video it never reads)."""
    store = EpisodeStore.open(store_path)
    recorded = store.attrs.get("task")
    if task and recorded and task != recorded:  # its states would be read as another task's
        raise DataError(f"{store_path}: a store of task {recorded}, not of task {task} (--task)")
    chosen = _lerobot_task(get_task(task or task_of(store) or DEFAULT_TASK))
    if store.n_episodes == 0:
        raise DataError(f"{store_path}: holds no episodes")
    _check_new(out)
    assert chosen.to_lerobot is not None
    episodes, keys = [], {}
    for i in range(store.n_episodes):
        ep = store.episode(i, [k for k in store.keys if images or k != IMAGE_KEY])
        features = chosen.to_lerobot(ep)
        for key, value in ep.items():
            if key == IMAGE_KEY and "observation.image" in features:
                keys[key] = {"feature": "observation.image", "shape": list(value.shape[1:]), "dtype": str(value.dtype)}
                continue
            name = VERBATIM + key
            keys[key] = {"feature": name, "shape": list(value.shape[1:]), "dtype": str(value.dtype)}
            features[name] = value.reshape(len(value), -1)
        episodes.append(features)
        interrupts.check()
    seeds, scores = store.episode_seeds(), store.episode_scores()
    record = {"source": str(store_path), "attrs": store.attrs, "keys": keys,
              "episode_seeds": None if seeds is None else [int(s) for s in seeds],
              "episode_scores": None if scores is None else [float(s) for s in scores],
              "task": chosen.name, "video": video}
    with _staged(out) as staging:
        staging.mkdir()
        write_lerobot(staging, episodes, chosen.fps, chosen.description, video, {"gpc": record})
    return {"episodes": len(episodes), "frames": int(store.n_steps), "out": str(out), "video": video if images else "no"}


def _restore(features: dict[str, np.ndarray], keys: dict[str, Any]) -> dict[str, np.ndarray]:
    out = {}
    for key, spec in keys.items():
        if spec["feature"] not in features:
            raise DataError(f"the dataset lacks {spec['feature']!r}, which meta/gpc.json lists")
        value = features[spec["feature"]]
        out[key] = value.reshape((len(value),) + tuple(spec["shape"])).astype(spec["dtype"])
    return out


def _gpc_record(path: Path, episodes: int) -> dict[str, Any]:
    """What gpc's export recorded beside a dataset, checked before it is trusted: a damaged one is named in one line."""
    from gpc.harness.files import read_json

    record = read_json(path)
    record = record.get("gpc") if isinstance(record, dict) else None
    if not isinstance(record, dict) or not isinstance(record.get("attrs"), dict) or not isinstance(record.get("keys"), dict):
        raise DataError(f"{path}: not gpc's record of an export (want {{'gpc': {{'attrs': {{...}}, 'keys': {{...}}}}}})")
    for key, spec in record["keys"].items():
        try:
            np.dtype(spec["dtype"])
            ok = all(isinstance(n, int) and n >= 0 for n in spec["shape"])
        except (TypeError, KeyError):
            ok = False
        if not ok:
            raise DataError(f"{path}: keys.{key}: want a shape of sizes and a numpy dtype, got {spec!r}"[:300])
    for name in ("episode_seeds", "episode_scores"):
        values = record.get(name)
        if values is not None and (not isinstance(values, list) or len(values) != episodes):
            raise DataError(f"{path}: {name}: want a list of {episodes} (one per episode of the dataset)")
    return record


def import_dataset(src: Path, out: Path, task: str | None = None) -> dict[str, Any]:
    """A LeRobot dataset as a gpc store in ``out`` (a new store): exactly, if gpc exported it."""
    if not is_lerobot_dataset(src):
        raise DataError(f"{src}: not a LeRobot dataset (no meta/info.json)")
    reader = LeRobotReader(src)
    record = _gpc_record(src / "meta" / META, reader.n_episodes) if (src / "meta" / META).is_file() else None
    chosen = _lerobot_task(get_task(task or (record or {}).get("task") or DEFAULT_TASK))
    _check_new(out)
    attrs = dict(record["attrs"]) if record else {"task": chosen.name}
    attrs["imported_from"] = {"path": str(src), "codebase_version": reader.info.get("codebase_version"), "fps": reader.fps}
    seeds = (record or {}).get("episode_seeds") or [-1] * reader.n_episodes
    scores = (record or {}).get("episode_scores") or [float("nan")] * reader.n_episodes
    assert chosen.from_lerobot is not None
    with _staged(out) as staging:
        store = EpisodeStore.create(staging, attrs)
        for i, features in enumerate(reader.episodes()):
            try:
                episode = _restore(features, record["keys"]) if record else chosen.from_lerobot(features)
                store.append_episode(episode, seed=int(seeds[i]), score=float(scores[i]))  # refuses NaN, changing nothing
            except DataError as exc:  # named by the dataset read, not the staging store that is removed
                raise DataError(f"{src}: episode {i}: {str(exc).removeprefix(f'{staging}: ')}") from None
            interrupts.check()
    return {"episodes": reader.n_episodes, "frames": int(sum(reader.lengths())), "out": str(out),
            "exact": record is not None, "task": chosen.name}
