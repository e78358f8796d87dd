"""MP4 writing with OpenCV (no ffmpeg binary needed)."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path

import cv2
import numpy as np

from gpc.datasets.errors import DataError
from gpc.datasets.fresh import missing_folders, remove_folders
from gpc.harness import interrupts
from gpc.harness.ownership import install, temporary_beside


def write_mp4(frames: Iterable[np.ndarray], path: str | Path, fps: int = 10, scale: int = 1) -> int:
    """Write RGB uint8 frames; returns how many were written. Written to a temporary name first, which a failure
    removes: the path holds a whole video or what it held before."""
    path = Path(path)
    if path.is_dir():
        raise DataError(f"{path}: is a folder; name the .mp4 file to write")
    folders = missing_folders(path.parent)  # made for the video; removed again if no video comes of it
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DataError(f"{path}: cannot be written ({exc.strerror or exc})") from None
    tmp = temporary_beside(path, ".partial.mp4")  # a new name: a file of the user's is never written over
    writer, n, done = None, 0, False
    try:
        for frame in frames:
            frame = np.asarray(frame, dtype=np.uint8)
            if scale != 1:
                frame = cv2.resize(frame, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
            if writer is None:
                h, w = frame.shape[:2]
                writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter.fourcc(*"mp4v"), fps, (w, h))
                if not writer.isOpened():
                    raise DataError(f"{path}: cannot be written (OpenCV cannot open an MP4 in {path.parent})")
            writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
            n += 1
            interrupts.check()
        if writer is None:
            raise ValueError(f"{path}: no frames to write")
        writer.release()
        if not tmp.is_file() or tmp.stat().st_size == 0:
            raise DataError(f"{path}: cannot be written (the disk may be full)")
        install(tmp, path)  # recorded as gpc's; a file there that gpc did not write is refused, not replaced
        done = True
    finally:
        if writer is not None:
            writer.release()
        tmp.unlink(missing_ok=True)
        if not done:
            remove_folders(folders)
    return n


def futures_panel(frame: np.ndarray, pictures: Sequence[np.ndarray], scores: Sequence[float], chosen: int) -> np.ndarray:
    """A frame's size in four: the scene (top left) and up to three candidates' predicted last steps, each as a
    picture ``(S, S, 3)`` uint8, labelled with its score; ``chosen`` (an index into ``pictures``) is framed in green.
    What the planner saw when it chose, for a task that draws no futures of its own (or image futures)."""
    size = frame.shape[0]
    half = size // 2
    panel = np.full_like(frame, 255)
    cells = [(0, 0), (0, half), (half, 0), (half, half)]
    tiles = [frame, *pictures[:3]]
    for n, ((y, x), tile) in enumerate(zip(cells, tiles)):
        small = cv2.resize(np.ascontiguousarray(tile, dtype=np.uint8), (half, half), interpolation=cv2.INTER_AREA)
        panel[y : y + half, x : x + half] = small
        if n == 0:
            continue
        k = n - 1
        colour = (0, 160, 0) if k == chosen else (90, 90, 90)
        cv2.rectangle(panel, (x, y), (x + half - 1, y + half - 1), colour, thickness=2 if k == chosen else 1)
        cv2.putText(panel, f"{scores[k]:.3f}", (x + 4, y + half - 6), cv2.FONT_HERSHEY_SIMPLEX, size / 900, colour, 1, cv2.LINE_AA)
    return panel
