"""`gpc collect` (a task's scripted expert or explorer) and `gpc record` (a policy or planner in closed loop):
episodes into a Zarr store, resumed by re-running the same command."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from gpc.cli.backend import backend_from_options, with_backend_options
from gpc.cli.eval_cmd import Checkpoint, Goal, PlannerKind, Threads, recipe_from_options, with_planning_options
from gpc.cli.limits import MAX_COUNT, MAX_PROCESSES, MAX_SEED
from gpc.tasks import DEFAULT_TASK

if TYPE_CHECKING:
    from gpc.harness.collection import CollectJob

Out = typer.Option(..., "--out", "-o", help="Zarr store to create or resume (a directory).")
Episodes = typer.Option(100, "--episodes", "-n", min=1, max=MAX_COUNT, help="Number of episodes (seeds SEED .. SEED+N-1).")
FirstSeed = typer.Option(0, "--seed", min=0, max=MAX_SEED, help="First environment seed; keep clear of the test seeds (100000+).")
Workers = typer.Option(1, "--workers", "-j", min=1, max=MAX_PROCESSES, help="Parallel worker processes (Ray workers with --backend ray); the store is identical for any count.")
MaxSteps = typer.Option(None, "--max-steps", min=1, max=MAX_COUNT, help="Steps per episode at most (default: the task's episode length).")
Overwrite = typer.Option(False, "--overwrite", help="Replace an existing store instead of resuming it.")


@with_backend_options
def collect(
    out: Path = Out,
    explore: bool = typer.Option(False, "--explore", help="Collect contact-rich exploration data instead of expert demonstrations."),
    episodes: int = Episodes,
    seed: int = FirstSeed,
    workers: int = Workers,
    task: str = typer.Option(DEFAULT_TASK, "--task", help="Task to collect from."),
    goal: str = typer.Option("fixed", "--goal", help="fixed: the standard goal; random: a per-seed goal (GPC's variant)."),
    images: bool = typer.Option(True, "--images/--no-images", help="Store the camera's frames (key img)."),
    max_steps: int | None = MaxSteps,
    overwrite: bool = Overwrite,
    dart: float | None = typer.Option(None, "--dart", help="DART demonstrations: run the expert's actions with correlated noise of this share of the action range (e.g. 0.02), store its own as expert_action."),
    dart_steps: float = typer.Option(4.0, "--dart-steps", help="With --dart: the noise's correlation time in control steps."),
    scale: dict | None = None,
) -> None:
    """Collect scripted episodes into a Zarr store; re-running the same command resumes it."""
    from gpc.harness.collection import CollectJob
    from gpc.tasks.base import ActionNoise

    backend = backend_from_options(scale)
    noise = ActionNoise(dart, dart_steps) if dart is not None else None
    _run(CollectJob(out=out, task=task, kind="explore" if explore else "expert", episodes=episodes, seed=seed,
                    workers=workers, goal=goal, images=images, max_steps=max_steps, overwrite=overwrite, backend=backend,
                    noise=noise))


@with_backend_options
@with_planning_options
def record(
    checkpoint: Checkpoint,
    planner: PlannerKind = "bc",
    planning: dict | None = None,
    scale: dict | None = None,
    out: Path = Out,
    episodes: int = Episodes,
    seed: int = FirstSeed,
    workers: int = Workers,
    batch: int = typer.Option(25, "--batch", min=1, max=MAX_COUNT, help="Episodes stepped in lockstep per controller call (gpc eval's default: the same episodes)."),
    threads: Threads = 1,
    goal: Goal = "fixed",
    max_steps: int | None = MaxSteps,
    overwrite: bool = Overwrite,
) -> None:
    """Record a policy's or planner's closed-loop episodes into a Zarr store, frames included.

    The episodes are those `gpc eval` scores for these seeds: e.g. the chunks GPC-OPT's ascent executes, with their
    true outcomes, to train the world model where the planner goes. Re-running the same command resumes it."""
    from gpc.harness.collection import CLOSED_LOOP, CollectJob, check_store_out

    assert planning is not None  # with_planning_options passes them
    check_store_out(out, overwrite)  # before any model loads; the rest of the checks need the controller's identity
    backend = backend_from_options(scale, planning["device"])
    recipe = recipe_from_options(checkpoint, planner, planning, goal, remote=backend is not None)
    assert recipe.task is not None  # make_recipe names the task
    _run(CollectJob(out=out, task=recipe.task, kind=CLOSED_LOOP, episodes=episodes, seed=seed, workers=workers,
                    goal=goal, max_steps=max_steps, overwrite=overwrite, controller=recipe, batch=batch, threads=threads,
                    backend=backend))


def _run(job: CollectJob) -> None:
    """Collect with a progress bar (started once the store is open, so a refusal prints no bar) and print the summary."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from gpc.harness.collection import check_job
    from gpc.harness.collection import collect as run_collect

    check_job(job)
    bar = Progress(TextColumn("[bold]collect[/] {task.description}"), BarColumn(), MofNCompleteColumn(),
                   TextColumn("mean score {task.fields[score]:.3f}"), TimeRemainingColumn())
    scores: list[float] = []

    def start(already: int) -> None:
        bar.add_task(job.kind, total=job.episodes, completed=already, score=float("nan"))
        bar.start()

    def tick(stats: dict) -> None:
        scores.append(stats["score"])
        bar.update(bar.task_ids[0], advance=1, score=sum(scores) / len(scores))

    try:
        summary = run_collect(job, on_start=start, on_episode=tick)
    finally:
        bar.stop()
    typer.echo(json.dumps(summary.__dict__, indent=2))


def register(app: typer.Typer) -> None:
    """Wire `gpc collect` and `gpc record` into the root CLI."""
    app.command("collect")(collect)
    app.command("record")(record)
