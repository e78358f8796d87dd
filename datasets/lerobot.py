"""LeRobot datasets (``LeRobotDataset`` directories) read and written with pyarrow and PyAV alone.

Read: codebase versions v2.0, v2.1 and v3.0 (``meta/info.json``; per-episode or concatenated
parquet data; per-episode or concatenated MP4 videos, or PNG images in the parquet). Vector
columns may be ``fixed_size_list`` (recorded) or ``list`` (converted hub datasets); a frame of a
concatenated video is the one presented at ``from_timestamp + frame_index / fps``.

Write: v3.0 as LeRobot 0.4 opens it offline (one data file, one video per camera, the
episodes table, ``tasks.parquet`` with the index metadata pandas needs, ``stats.json``).
Videos are H.264: ``lossless`` (``libx264rgb``, qp 0: frames come back bit-exact) or ``h264``
(yuv420p, crf 18, what LeRobot-style datasets hold). Nothing here knows a task: features go in
and out under their LeRobot names (``gpc.harness.lerobot_data`` maps them to a task's keys).
``docs/data.md`` has the layout.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from gpc.datasets.errors import DataError
from gpc.datasets.jsonfile import read_json

DEFAULT_FEATURES = ("timestamp", "frame_index", "episode_index", "index", "task_index")
VIDEO_CODECS = ("lossless", "h264")
TOLERANCE_S = 1e-4  # LeRobot's tolerance between a frame's timestamp and the video's


def _imports() -> tuple[Any, Any]:
    try:
        import av
        import pyarrow.parquet as pq
    except ImportError as exc:  # pragma: no cover - both are dependencies; a broken install says which
        raise DataError(f"LeRobot datasets need pyarrow and av ({exc.name} is missing: pip install pyarrow av)") from None
    return pq, av


def is_lerobot_dataset(path: str | os.PathLike) -> bool:
    return (Path(path) / "meta" / "info.json").is_file()


@dataclass(frozen=True)
class Feature:
    """One LeRobot feature: its dtype (a numpy name, ``video`` or ``image``) and the shape of one frame."""

    name: str
    dtype: str
    shape: tuple[int, ...]

    @property
    def visual(self) -> bool:
        return self.dtype in ("video", "image")

    @property
    def frame_shape(self) -> tuple[int, ...]:
        """Images as (H, W, C) whatever order the dataset declared."""
        if self.visual and len(self.shape) == 3 and self.shape[0] in (1, 3, 4) and self.shape[2] not in (1, 3, 4):
            return (self.shape[1], self.shape[2], self.shape[0])
        return self.shape


class LeRobotReader:
    """The episodes of a LeRobot dataset directory, one at a time, as ``{feature: (T, *shape)}`` arrays."""

    def __init__(self, root: str | os.PathLike) -> None:
        self.root = Path(root)
        info_path = self.root / "meta" / "info.json"
        if not info_path.is_file():
            raise DataError(f"{self.root}: not a LeRobot dataset (no meta/info.json)")
        info = read_json(info_path)
        if not isinstance(info, dict) or "features" not in info or "fps" not in info:
            raise DataError(f"{info_path}: has no features or fps (not a LeRobot dataset's info.json)")
        self.info = info
        self.version = str(info.get("codebase_version", "")).lstrip("v")
        if self.version.split(".")[0] not in ("2", "3"):
            raise DataError(f"{info_path}: codebase_version {info.get('codebase_version')!r}: gpc reads v2.0, v2.1 and v3.0")
        self.fps = float(info["fps"])
        self.features: dict[str, Feature] = {}
        for name, spec in info["features"].items():
            if name in DEFAULT_FEATURES:
                continue
            if not isinstance(spec, dict) or "dtype" not in spec or "shape" not in spec:
                raise DataError(f"{info_path}: feature {name!r} has no dtype and shape")
            self.features[name] = Feature(name, str(spec["dtype"]), tuple(int(s) for s in spec["shape"]))
        self._episodes = self._episode_table()

    # ------------------------------------------------------------------ metadata
    def _episode_table(self) -> list[dict[str, Any]]:
        pq, _ = _imports()
        meta = self.root / "meta"
        if self.version.startswith("3"):
            files = sorted((meta / "episodes").glob("*/*.parquet"))
            if not files:
                raise DataError(f"{meta / 'episodes'}: no episodes parquet (a v3.0 dataset lists its episodes there)")
            rows: list[dict[str, Any]] = []
            for f in files:
                table = pq.read_table(f, columns=[c for c in pq.read_schema(f).names if not c.startswith("stats/")])
                rows.extend(table.to_pylist())
        else:
            path = meta / "episodes.jsonl"
            try:
                rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
            except (OSError, ValueError) as exc:
                raise DataError(f"{path}: cannot be read as JSON lines ({exc})") from None
            start = 0
            for row in sorted(rows, key=lambda r: r["episode_index"]):
                row["dataset_from_index"], start = start, start + int(row["length"])
                row["dataset_to_index"] = start
        rows.sort(key=lambda r: int(r["episode_index"]))
        if [int(r["episode_index"]) for r in rows] != list(range(len(rows))):
            raise DataError(f"{meta}: episode indices are not 0..{len(rows) - 1}")
        return rows

    @property
    def n_episodes(self) -> int:
        return len(self._episodes)

    def lengths(self) -> list[int]:
        return [int(r["length"]) for r in self._episodes]

    def tasks(self) -> dict[int, str]:
        """task_index -> task string."""
        pq, _ = _imports()
        meta = self.root / "meta"
        if (meta / "tasks.parquet").is_file():
            table = pq.read_table(meta / "tasks.parquet")
            text = next((c for c in table.column_names if c != "task_index"), None)
            if text is None:
                return {}
            return dict(zip(table.column("task_index").to_pylist(), table.column(text).to_pylist()))
        if (meta / "tasks.jsonl").is_file():
            rows = [json.loads(line) for line in (meta / "tasks.jsonl").read_text().splitlines() if line.strip()]
            return {int(r["task_index"]): str(r["task"]) for r in rows}
        return {}

    # ------------------------------------------------------------------ data
    def _data_file(self, row: Mapping[str, Any]) -> Path:
        template = self.info.get("data_path")
        if not template:
            raise DataError(f"{self.root / 'meta' / 'info.json'}: no data_path")
        if self.version.startswith("3"):
            return self.root / template.format(chunk_index=row["data/chunk_index"], file_index=row["data/file_index"])
        e = int(row["episode_index"])
        return self.root / template.format(episode_chunk=e // int(self.info.get("chunks_size", 1000)), episode_index=e)

    def _video_file(self, row: Mapping[str, Any], key: str) -> tuple[Path, float]:
        template = self.info.get("video_path")
        if not template:
            raise DataError(f"{self.root / 'meta' / 'info.json'}: feature {key!r} is a video but there is no video_path")
        if self.version.startswith("3"):
            path = template.format(video_key=key, chunk_index=row[f"videos/{key}/chunk_index"],
                                   file_index=row[f"videos/{key}/file_index"])
            return self.root / path, float(row[f"videos/{key}/from_timestamp"])
        e = int(row["episode_index"])
        chunk = e // int(self.info.get("chunks_size", 1000))
        return self.root / template.format(episode_chunk=chunk, video_key=key, episode_index=e), 0.0

    def episodes(self) -> Iterator[dict[str, np.ndarray]]:
        """Every episode in order: each feature's frames, rows ordered by frame_index."""
        pq, _ = _imports()
        cache: tuple[Path, Any] | None = None
        for row in self._episodes:
            path = self._data_file(row)
            if cache is None or cache[0] != path:
                if not path.is_file():
                    raise DataError(f"{path}: missing (episode {row['episode_index']}'s data)")
                cache = (path, pq.read_table(path))
            table = cache[1]
            index = np.asarray(table.column("episode_index").to_numpy(zero_copy_only=False))
            rows = np.flatnonzero(index == int(row["episode_index"]))
            frames = np.asarray(table.column("frame_index").to_numpy(zero_copy_only=False))[rows]
            rows = rows[np.argsort(frames, kind="stable")]
            if len(rows) != int(row["length"]):
                raise DataError(f"{path}: episode {row['episode_index']} has {len(rows)} rows, its length is {row['length']}")
            part = table.take(rows)
            out: dict[str, np.ndarray] = {}
            for name, feature in self.features.items():
                if feature.dtype == "video":
                    out[name] = self._frames(row, name, len(rows))
                elif name not in part.column_names:
                    raise DataError(f"{path}: no column {name!r} (info.json lists it)")
                elif feature.dtype == "image":
                    out[name] = self._images(part.column(name), path, name)
                elif feature.dtype != "string":
                    out[name] = self._values(part.column(name), feature, path)
            yield out

    def _values(self, column: Any, feature: Feature, path: Path) -> np.ndarray:
        import pyarrow as pa

        n, size = len(column), int(np.prod(feature.shape))
        column = column.combine_chunks() if hasattr(column, "combine_chunks") else column
        while pa.types.is_list(column.type) or pa.types.is_fixed_size_list(column.type) or pa.types.is_large_list(column.type):
            column = column.flatten()
        flat = np.asarray(column.to_numpy(zero_copy_only=False))
        if flat.size != n * size:
            raise DataError(f"{path}: column {feature.name!r} holds {flat.size // max(n, 1)} values per frame, "
                            f"info.json says {list(feature.shape)}")
        return flat.reshape((n,) + feature.shape).astype(feature.dtype if feature.dtype != "bool" else np.bool_)

    def _images(self, column: Any, path: Path, name: str) -> np.ndarray:
        import cv2

        frames = []
        for item in column.to_pylist():
            data = item.get("bytes") if isinstance(item, dict) else None
            if data is None and isinstance(item, dict) and item.get("path"):
                data = (self.root / item["path"]).read_bytes()
            image = cv2.imdecode(np.frombuffer(data or b"", np.uint8), cv2.IMREAD_COLOR) if data else None
            if image is None:
                raise DataError(f"{path}: an image of {name!r} cannot be decoded")
            frames.append(cv2.cvtColor(image, cv2.COLOR_BGR2RGB))
        return np.stack(frames)

    def _frames(self, row: Mapping[str, Any], key: str, length: int) -> np.ndarray:
        _, av = _imports()
        path, start = self._video_file(row, key)
        if not path.is_file():
            raise DataError(f"{path}: missing (episode {row['episode_index']}'s {key} video)")
        first = round(start * self.fps)
        frames: dict[int, np.ndarray] = {}
        try:
            with av.open(str(path)) as container:
                stream = container.streams.video[0]
                if start > 0:
                    container.seek(int(start / stream.time_base), stream=stream, backward=True)
                for frame in container.decode(stream):
                    seconds = float(frame.pts * stream.time_base)
                    n = round(seconds * self.fps)
                    if abs(seconds - n / self.fps) > TOLERANCE_S:
                        raise DataError(f"{path}: a frame at {seconds:.6f} s is off the {self.fps:g} fps grid")
                    if n >= first + length:
                        break
                    if n >= first:
                        frames[n - first] = frame.to_ndarray(format="rgb24")
        except av.error.FFmpegError as exc:
            raise DataError(f"{path}: cannot be decoded ({exc})") from None
        if len(frames) != length:
            raise DataError(f"{path}: episode {row['episode_index']} needs {length} frames from {start:.3f} s, found {len(frames)}")
        return np.stack([frames[i] for i in range(length)])


# ---------------------------------------------------------------------- writing
def _feature_spec(name: str, value: np.ndarray, video: str | None) -> dict[str, Any]:
    if value.dtype == np.uint8 and value.ndim == 4:
        h, w, c = value.shape[1:]
        spec: dict[str, Any] = {"dtype": "video", "shape": [h, w, c], "names": ["height", "width", "channels"]}
        spec["info"] = {"video.height": h, "video.width": w, "video.codec": "h264",
                        "video.pix_fmt": "rgb24" if video == "lossless" else "yuv420p", "video.is_depth_map": False,
                        "video.fps": None, "video.channels": c, "has_audio": False}
        return spec
    return {"dtype": str(value.dtype), "shape": list(value.shape[1:]) or [1], "names": None}


def _stats(value: np.ndarray, visual: bool) -> dict[str, Any]:
    if visual:
        x = value.reshape(-1, value.shape[-1]).astype(np.float64) / 255.0
        shape: tuple[int, ...] = (value.shape[-1], 1, 1)
    else:
        x = value.reshape(len(value), -1).astype(np.float64)
        shape = value.shape[1:] or (1,)
    out = {name: fn(x, axis=0).reshape(shape).tolist() for name, fn in
           (("min", np.min), ("max", np.max), ("mean", np.mean), ("std", np.std))}
    out["count"] = [int(len(value))]
    return out


def _encode(frames: Sequence[np.ndarray], path: Path, fps: int, codec: str) -> None:
    _, av = _imports()
    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), mode="w") as container:
        options = {"qp": "0", "g": "2"} if codec == "lossless" else {"crf": "18", "g": "2"}
        stream = container.add_stream("libx264rgb" if codec == "lossless" else "libx264", rate=fps, options=options)
        stream.height, stream.width = frames[0].shape[:2]
        stream.pix_fmt = "rgb24" if codec == "lossless" else "yuv420p"
        stream.time_base = Fraction(1, fps)
        for i, image in enumerate(frames):
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="rgb24")
            frame.pts = i
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


def _fixed_lists(value: np.ndarray) -> Any:
    import pyarrow as pa

    flat = value.reshape(len(value), -1)
    arrow = pa.array(flat.reshape(-1))
    return arrow if flat.shape[1] == 1 else pa.FixedSizeListArray.from_arrays(arrow, flat.shape[1])


def _tasks_table(tasks: Sequence[str]) -> Any:
    """tasks.parquet as pandas writes it (LeRobot reads it with pandas: the task string is the index)."""
    import pyarrow as pa

    meta = {"index_columns": ["__index_level_0__"], "column_indexes": [],
            "columns": [{"name": "task_index", "field_name": "task_index", "pandas_type": "int64", "numpy_type": "int64",
                         "metadata": None},
                        {"name": None, "field_name": "__index_level_0__", "pandas_type": "unicode", "numpy_type": "object",
                         "metadata": None}],
            "creator": {"library": "gpc"}, "pandas_version": "2.2.0"}
    table = pa.table({"task_index": pa.array(range(len(tasks)), pa.int64()), "__index_level_0__": pa.array(list(tasks), pa.string())})
    return table.replace_schema_metadata({b"pandas": json.dumps(meta).encode()})


def write_lerobot(root: Path, episodes: Sequence[Mapping[str, np.ndarray]], fps: int, task: str, video: str = "lossless",
                  extra_meta: Mapping[str, Any] | None = None) -> None:
    """Write ``episodes`` (``{feature: (T, ...)}``; uint8 (T, H, W, 3) arrays become videos) as a v3.0 dataset in
    ``root`` (a new directory). ``extra_meta`` goes to ``meta/gpc.json`` (LeRobot ignores it)."""
    import pyarrow as pa

    pq, _ = _imports()
    if video not in VIDEO_CODECS:
        raise ValueError(f"--video {video!r}: use one of {', '.join(VIDEO_CODECS)}")
    if not episodes:
        raise DataError(f"{root}: no episodes to write")
    names = list(episodes[0])
    for i, ep in enumerate(episodes):
        if list(ep) != names:
            raise DataError(f"episode {i} has features {sorted(ep)}, episode 0 has {sorted(names)}")
    visual = [n for n in names if episodes[0][n].dtype == np.uint8 and episodes[0][n].ndim == 4]
    lengths = [len(next(iter(ep.values()))) for ep in episodes]
    starts = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
    total = int(starts[-1])
    columns: dict[str, Any] = {}
    for name in names:
        if name in visual:
            continue
        columns[name] = _fixed_lists(np.concatenate([ep[name] for ep in episodes]))
    frame_index = np.concatenate([np.arange(n) for n in lengths]).astype(np.int64)
    columns["timestamp"] = pa.array((frame_index / fps).astype(np.float32))
    columns["frame_index"] = pa.array(frame_index)
    columns["episode_index"] = pa.array(np.repeat(np.arange(len(episodes)), lengths).astype(np.int64))
    columns["index"] = pa.array(np.arange(total, dtype=np.int64))
    columns["task_index"] = pa.array(np.zeros(total, np.int64))
    data_path = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
    (root / "data" / "chunk-000").mkdir(parents=True)
    pq.write_table(pa.table(columns), root / data_path.format(chunk_index=0, file_index=0))
    video_path = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
    for name in visual:
        _encode([f for ep in episodes for f in ep[name]], root / video_path.format(video_key=name, chunk_index=0, file_index=0),
                fps, video)
    ep_cols: dict[str, Any] = {
        "episode_index": pa.array(np.arange(len(episodes), dtype=np.int64)),
        "tasks": pa.array([[task]] * len(episodes), pa.list_(pa.string())),
        "length": pa.array(np.asarray(lengths, np.int64)),
        "data/chunk_index": pa.array(np.zeros(len(episodes), np.int64)),
        "data/file_index": pa.array(np.zeros(len(episodes), np.int64)),
        "dataset_from_index": pa.array(starts[:-1]), "dataset_to_index": pa.array(starts[1:]),
    }
    for name in visual:
        ep_cols[f"videos/{name}/chunk_index"] = pa.array(np.zeros(len(episodes), np.int64))
        ep_cols[f"videos/{name}/file_index"] = pa.array(np.zeros(len(episodes), np.int64))
        ep_cols[f"videos/{name}/from_timestamp"] = pa.array(starts[:-1] / fps)
        ep_cols[f"videos/{name}/to_timestamp"] = pa.array(starts[1:] / fps)
    ep_cols["meta/episodes/chunk_index"] = pa.array(np.zeros(len(episodes), np.int64))
    ep_cols["meta/episodes/file_index"] = pa.array(np.zeros(len(episodes), np.int64))
    (root / "meta" / "episodes" / "chunk-000").mkdir(parents=True)
    pq.write_table(pa.table(ep_cols), root / "meta" / "episodes" / "chunk-000" / "file-000.parquet")
    pq.write_table(_tasks_table([task]), root / "meta" / "tasks.parquet")
    features = {n: _feature_spec(n, episodes[0][n], video if n in visual else None) for n in names}
    for spec in features.values():
        if spec["dtype"] == "video":
            spec["info"]["video.fps"] = fps
    features.update({"timestamp": {"dtype": "float32", "shape": [1], "names": None},
                     **{n: {"dtype": "int64", "shape": [1], "names": None} for n in DEFAULT_FEATURES[1:]}})
    stats = {n: _stats(np.concatenate([ep[n] for ep in episodes]), n in visual) for n in names}
    (root / "meta" / "stats.json").write_text(json.dumps(stats, indent=2))
    info = {"codebase_version": "v3.0", "robot_type": None, "total_episodes": len(episodes), "total_frames": total,
            "total_tasks": 1, "chunks_size": 1000, "data_files_size_in_mb": 100, "video_files_size_in_mb": 200, "fps": fps,
            "splits": {"train": f"0:{len(episodes)}"}, "data_path": data_path, "video_path": video_path if visual else None,
            "features": features}
    (root / "meta" / "info.json").write_text(json.dumps(info, indent=4))
    if extra_meta is not None:
        (root / "meta" / "gpc.json").write_text(json.dumps(extra_meta, indent=2))
