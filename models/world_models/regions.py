"""Reading a region with extent but no pose (Triangle Drawing's ink) from predicted frames, pixel by pixel.

An object's error is how far its pose is off; ink has no pose, and what a planner scoring a drawing needs from a
predicted frame is where the ink lies. ``RegionReadout`` marks each region's pixels by colour (the task's
``FrameLayout.regions``) and counts the pixels where the prediction's mask and the recorded frame's disagree,
beside the "nothing changes" baseline (the last context frame's mask), on every window and on the windows where
the region changes.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from gpc.datasets.layout import RegionLook, TaskLayout


@dataclass(frozen=True)
class RegionReadout:
    """Every region of a task's frames, read by colour; ``changed_pixels``: a window "changes" the region when its
    recorded final frame differs from the last context frame in more than this many of the region's pixels."""

    regions: tuple[RegionLook, ...]
    changed_pixels: int = 4

    @classmethod
    def from_layout(cls, layout: TaskLayout) -> RegionReadout | None:
        """The task's regions, or None where its frames name none."""
        frame = layout.frame
        return cls(frame.regions) if frame is not None and frame.regions else None

    @staticmethod
    def mask(region: RegionLook, frames: np.ndarray) -> np.ndarray:
        """``(..., S, S, 3)`` uint8 -> ``(..., S, S)`` bool: the pixels within the region's tolerance of one of its colours."""
        x = frames.astype(np.float32)
        dist = np.min([np.linalg.norm(x - np.asarray(c, np.float32), axis=-1) for c in region.colours], axis=0)
        return dist < region.tolerance

    def figures(self, model: np.ndarray, true: np.ndarray, last: np.ndarray) -> dict[str, Any]:
        """``model`` / ``true``: ``(N, T, S, S, 3)``, ``last``: ``(N, S, S, 3)`` uint8 -> per region: wrong pixels per
        step (model, baseline), and on the changing windows' final frame (with the model / baseline ratio)."""
        out: dict[str, Any] = {}
        for region in self.regions:
            pred, rec = self.mask(region, model), self.mask(region, true)
            still = np.broadcast_to(self.mask(region, last)[:, None], rec.shape)
            wrong = {"model": (pred != rec).sum(axis=(2, 3)), "baseline": (still != rec).sum(axis=(2, 3))}  # (N, T)
            changing = wrong["baseline"][:, -1] > self.changed_pixels
            figures: dict[str, Any] = {
                "pixels_true_mean": float(rec.sum(axis=(2, 3)).mean()), "changing_windows": int(changing.sum()),
                "per_step": {k: v.mean(axis=0).tolist() for k, v in wrong.items()}, "final_changing": {}}
            if changing.any():
                final = {k: float(v[changing, -1].mean()) for k, v in wrong.items()}
                figures["final_changing"] = {**final, "ratio": final["model"] / final["baseline"]}
            out[region.name] = figures
        return out

    def describe(self) -> dict[str, Any]:
        return {"pose": "regions", **asdict(self)}


def regions_markdown(figures: dict[str, Any], steps: list[int]) -> list[str]:
    """Lines for a report: each region's wrong pixels per predicted frame, then on the changing windows' last frame."""
    lines = ["", "Regions read by colour: pixels where the predicted frame's region and the recorded one's disagree "
             "(model / nothing-changes baseline; lower is better).", "",
             "| step (actions) | " + " | ".join(f"{name} wrong px" for name in figures) + " |", "|---|" + "---|" * len(figures)]
    for i, actions in enumerate(steps):
        cells = [f"{f['per_step']['model'][i]:.1f} / {f['per_step']['baseline'][i]:.1f}" for f in figures.values()]
        lines.append(f"| {i + 1} ({actions}) | " + " | ".join(cells) + " |")
    lines.append("")
    for name, f in figures.items():
        final = f["final_changing"]
        lines.append(f"{name}: on the {f['changing_windows']} windows where it changes, the last frame has "
                     + (f"{final['model']:.1f} wrong px against {final['baseline']:.1f} for nothing changes "
                        f"(ratio {final['ratio']:.2f}); " if final else "no figures; ")
                     + f"recorded frames hold {f['pixels_true_mean']:.0f} of its pixels on average.")
    return lines
