"""Reading a task's state from predicted frames with a learned state reader: the readout of scenes colour cannot place.

A perspective camera's shaded boxes (Block Stacking) give no planar centroid, and a centroid says nothing of a cube's
height. The reader here is the learned image reward's (``gpc train reward`` on a task scored by its own state
reward), so these are the errors a planner ranking predicted frames with that reward faces. Predicted, recorded and
last context frames are read alike, so the reader's own bias cancels; beside them, the reader's error on recorded
frames against the recorded states says how small an error it can tell apart at all.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from gpc.datasets.layout import TaskLayout

SOURCES = ("model", "baseline")


@dataclass(frozen=True)
class Quantity:
    """One length a readout compares: the Euclidean distance over ``entries`` of the state (a position, a height).

    A window "moves" it when the state read from the recorded final frame lies more than ``moved`` from the one read
    from the last context frame over ``moved_entries`` (an object's whole position, height included); None: judged on
    every window only (the agent).
    """

    name: str
    entries: tuple[int, ...]
    moved_entries: tuple[int, ...] = ()
    moved: float | None = None


def quantities(layout: TaskLayout) -> tuple[Quantity, ...]:
    """Each object's planar position and, in a 3-D scene, its height (it moves when its position, height included,
    changes by a quarter of its size), then the agent's entries."""
    out: list[Quantity] = []
    for obj in layout.objects:
        where = obj.pose[:2] + ((obj.height,) if obj.height is not None else ())
        out.append(Quantity(obj.name, obj.pose[:2], where, 0.25 * obj.size))
        if obj.height is not None:
            out.append(Quantity(f"{obj.name} height", (obj.height,), where, 0.25 * obj.size))
    if layout.state.agent_xy:
        out.append(Quantity("agent", tuple(layout.state.agent_xy)))
    return tuple(out)


class StateReadout:
    """Every quantity of ``quantities(layout)``, read from frames by a learned state reader (frames in [0, 1] ->
    ``(N, D)`` states in state units)."""

    def __init__(self, reader: torch.nn.Module, layout: TaskLayout, source: str, batch_size: int = 256) -> None:
        self.reader, self.layout, self.source, self.batch_size = reader.eval(), layout, source, batch_size
        self.quantities = quantities(layout)

    @torch.no_grad()
    def states(self, frames: np.ndarray) -> np.ndarray:
        """``(..., S, S, 3)`` uint8 -> ``(..., D)`` float64 states as the reader reads them."""
        flat = frames.reshape((-1,) + frames.shape[-3:])
        x = torch.from_numpy(np.ascontiguousarray(flat)).movedim(-1, 1).float() / 255.0
        parts = [self.reader(x[i : i + self.batch_size]).double() for i in range(0, len(x), self.batch_size)]
        read = torch.cat(parts).numpy() if parts else np.zeros((0, self.layout.state.dim))
        return read.reshape(frames.shape[:-3] + (read.shape[-1],))

    def figures(self, model: np.ndarray, true: np.ndarray, last: np.ndarray, recorded: np.ndarray | None = None) -> dict[str, Any]:
        """``model`` / ``true``: ``(N, T, S, S, 3)``, ``last``: ``(N, S, S, 3)`` uint8; ``recorded``: ``(N, T, D)`` the
        states behind ``true`` -> per quantity: errors per step (model, baseline), on the moving windows' final
        frame (with the model / baseline ratio), and the reader's own error on the recorded frames."""
        read = {"model": self.states(model), "true": self.states(true)}
        read["baseline"] = np.broadcast_to(self.states(last)[:, None], read["true"].shape)
        out: dict[str, Any] = {}
        for q in self.quantities:
            e = list(q.entries)
            errors = {name: np.linalg.norm(read[name][..., e] - read["true"][..., e], axis=-1) for name in SOURCES}  # (N, T)
            fig: dict[str, Any] = {"per_step": {name: v.mean(axis=0).tolist() for name, v in errors.items()},
                                   "final_moving": {}}
            if recorded is not None:
                fig["reader_error"] = float(np.linalg.norm(read["true"][..., e] - recorded[..., e], axis=-1).mean())
            if q.moved is not None:
                m = list(q.moved_entries)
                moving = np.linalg.norm(read["true"][:, -1, m] - read["baseline"][:, -1, m], axis=-1) > q.moved
                fig["moving_windows"] = int(moving.sum())
                if moving.any():
                    final = {name: float(v[moving, -1].mean()) for name, v in errors.items()}
                    fig["final_moving"] = {**final, "ratio": final["model"] / final["baseline"] if final["baseline"] > 0
                                           else float("nan")}
            out[q.name] = fig
        return out

    def describe(self) -> dict[str, Any]:
        return {"pose": "state reader", "checkpoint": self.source, "unit": self.layout.unit, "unit_scale": self.layout.unit_scale,
                "quantities": [{"name": q.name, "entries": list(q.entries), "moved": q.moved} for q in self.quantities]}


def state_readout_markdown(figures: dict[str, Any], config: dict[str, Any], steps: list[int]) -> list[str]:
    """Lines for a report: each quantity's error per predicted frame (in the task's unit), then on the final frame of
    the windows where it moves, then the reader's own error."""
    unit, scale = config["unit"], config["unit_scale"]
    lines = ["", f"State read from each frame by the learned state reader ({config['checkpoint']}): distance between what it "
             f"reads from the predicted and from the recorded frame, {unit} (model / nothing-moves baseline; lower is better).",
             "", "| step (actions) | " + " | ".join(figures) + " |", "|---|" + "---|" * len(figures)]
    for i, actions in enumerate(steps):
        cells = [f"{f['per_step']['model'][i] * scale:.1f} / {f['per_step']['baseline'][i] * scale:.1f}" for f in figures.values()]
        lines.append(f"| {i + 1} ({actions}) | " + " | ".join(cells) + " |")
    lines.append("")
    for name, f in figures.items():
        if "moving_windows" in f:
            final = f["final_moving"]
            lines.append(f"{name}: on the {f['moving_windows']} windows where it moves, the last frame is off by "
                         + (f"{final['model'] * scale:.1f} {unit} against {final['baseline'] * scale:.1f} for nothing moves "
                            f"(ratio {final['ratio']:.2f})." if final else "- (no such window)."))
    floor = {name: f["reader_error"] for name, f in figures.items() if "reader_error" in f}
    if floor:
        lines.append("The reader's own error on the recorded frames against the recorded states: "
                     + ", ".join(f"{name} {v * scale:.1f} {unit}" for name, v in floor.items()) + ".")
    return lines
