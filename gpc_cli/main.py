"""`gpc`: collect data, inspect stores, check the simulator, train, evaluate and plan."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from gpc.cli.collect_cmd import register as register_collect
from gpc.cli.errors import OneLineErrors
from gpc.cli.eval_cmd import eval_app
from gpc.cli.eval_cmd import register as register_eval
from gpc.cli.limits import MAX_COUNT
from gpc.cli.reward import evaluate as eval_reward
from gpc.cli.reward import train as train_reward
from gpc.cli.serve_cmd import register as register_serve
from gpc.cli.train import train_app
from gpc.cli.world_model import evaluate as eval_world_model
from gpc.cli.world_model import train as train_world_model
from gpc.tasks import DEFAULT_TASK, get_task

app = typer.Typer(
    help="Generative Predictive Control: improve a frozen diffusion policy with a learned world model.",
    cls=OneLineErrors, no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False,
)
data_app = typer.Typer(help="Inspect episode stores.", no_args_is_help=True)
app.add_typer(data_app, name="data")
app.add_typer(train_app, name="train")
register_collect(app)
register_eval(app)
register_serve(app)
train_app.command("world-model")(train_world_model)
eval_app.command("world-model")(eval_world_model)
train_app.command("reward")(train_reward)
eval_app.command("reward")(eval_reward)


@data_app.command("info")
def data_info(
    path: Path = typer.Argument(..., help="Zarr episode store."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON instead of a table."),
) -> None:
    """Episodes, steps, keys and shapes, contact fraction and score distribution of a store."""
    from gpc.cli.reports import print_description
    from gpc.harness.stores import describe_store

    info = describe_store(path)
    typer.echo(json.dumps(info, indent=2)) if as_json else print_description(info)


@data_app.command("video")
def data_video(
    path: Path = typer.Argument(..., help="Zarr episode store."),
    episode: int = typer.Option(0, "--episode", "-e", help="Episode index (negative counts from the end)."),
    out: Path | None = typer.Option(None, "--out", "-o", help="MP4 to write (default: <store>_ep<i>.mp4)."),
) -> None:
    """Write one episode as an MP4."""
    from gpc.harness.stores import episode_video

    written = episode_video(path, episode, out)
    typer.echo(f"wrote {written}")


@data_app.command("import")
def data_import(
    src: Path = typer.Argument(..., help="A LeRobot dataset directory (v2.0, v2.1 or v3.0: meta/info.json, parquet, MP4)."),
    out: Path = typer.Option(..., "--out", "-o", help="Zarr store to create (a new path)."),
    task: str | None = typer.Option(None, "--task", help="Task whose keys the features map to (default: the one gpc exported it from, else pusht)."),
) -> None:
    """Convert a LeRobot dataset into a gpc episode store (exactly, when gpc exported it)."""
    from gpc.datasets.locks import exclusive
    from gpc.harness.lerobot_data import import_dataset

    with exclusive(out, "store"):
        done = import_dataset(src, out, task)
    how = "restored exactly from its gpc.* features" if done["exact"] else f"features mapped by task {done['task']}"
    typer.echo(f"wrote {done['out']}: {done['episodes']} episodes, {done['frames']} steps ({how})")


@data_app.command("export")
def data_export(
    path: Path = typer.Argument(..., help="Zarr episode store."),
    out: Path = typer.Option(..., "--out", "-o", help="LeRobot dataset directory to create (a new path)."),
    video: str = typer.Option("lossless", "--video", help="lossless (H.264 RGB, qp 0: frames exact) or h264 (yuv420p, crf 18, small)."),
    task: str | None = typer.Option(None, "--task", help="Task the store belongs to (default: its record)."),
    images: bool = typer.Option(True, "--images/--no-images", help="Include the camera frames (a keypoint policy does not read them)."),
) -> None:
    """Write a store as a LeRobot v3.0 dataset (LeRobot trains on it; `gpc data import` restores it)."""
    from gpc.datasets.locks import exclusive
    from gpc.harness.lerobot_data import export_store

    with exclusive(out, "dataset"):
        done = export_store(path, out, video, task, images)
    typer.echo(f"wrote {done['out']}: {done['episodes']} episodes, {done['frames']} frames, {done['video']} video")


@app.command("check-sim")
def check_sim(
    data: Path = typer.Option(..., "--data", help="A recorded store of the task (e.g. Diffusion Policy's Push-T data)."),
    episodes: int = typer.Option(0, "--episodes", min=0, max=MAX_COUNT, help="Check only the first N episodes (0: all)."),
    frame_stride: int = typer.Option(10, "--frame-stride", min=1, max=MAX_COUNT, help="Compare every k-th recorded frame."),
    out: Path | None = typer.Option(None, "--out", help="Also write the figures as JSON here."),
    task: str = typer.Option(DEFAULT_TASK, "--task", help="Task whose simulator replays the store."),
) -> None:
    """Replay recorded actions and re-render recorded states; print how closely they match."""
    from gpc.cli.reports import print_check
    from gpc.harness import interrupts
    from gpc.harness.files import check_file_out, write_atomic

    check = get_task(task).check_replay
    if check is None:
        raise ValueError(f"--task {task}: this task has no replay check")
    if out:
        check_file_out(out, ".json")
    report = check(data, episodes, frame_stride)
    interrupts.check()
    print_check(report)
    if out:
        out.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(out, json.dumps(report, indent=2))


@app.command("inspect")
def inspect_policy(
    path: Path = typer.Argument(..., help="A gpc policy checkpoint, a LeRobot policy directory or a Diffusion Policy .ckpt."),
    policy_format: str | None = typer.Option(None, "--policy-format", help="gpc, lerobot or diffusion_policy (default: detected)."),
    task: str | None = typer.Option(None, "--task", help="Task a LeRobot or Diffusion Policy checkpoint acts in (default: pusht)."),
    as_json: bool = typer.Option(False, "--json", help="Print the description as JSON."),
) -> None:
    """What a policy file holds, as gpc loads it: format, observations, horizons, sampler, size, normaliser ranges."""
    from gpc.cli.reports import print_policy
    from gpc.harness.policies import describe, load_policy

    info = describe(load_policy(path, task, policy_format))
    if as_json:
        typer.echo(json.dumps(info, indent=2))
    else:
        print_policy(info)


@app.command("export")
def export(
    path: Path = typer.Argument(..., help="A gpc checkpoint: policy, world model or reward."),
    out: Path = typer.Option(..., "--out", "-o", help="The .ckpt file to write (a new path)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace a file already at --out."),
    half: bool = typer.Option(False, "--half", help="Store the network's weights in float16: half the file, "
                              "the normaliser kept exact; the model then plans with rounded weights, so measure "
                              "figures with the exported file."),
) -> None:
    """A checkpoint to plan with and share: config, normaliser and weights, without the optimiser's state
    (the policy keeps only the averaged weights it samples with: a quarter of Lightning's file)."""
    import io

    import torch

    from gpc.datasets.errors import DataError
    from gpc.harness.files import check_file_out, write_bytes_atomic
    from gpc.harness.ownership import adopt
    from gpc.models.policy.formats import DIFFUSION_POLICY, GPC, LEROBOT, detect_format
    from gpc.models.training.checkpoint import for_planning, read_checkpoint

    def older_export(file: Path) -> bool:  # a gpc checkpoint written before gpc kept its ownership record
        return bool(read_checkpoint(file, None))

    check_file_out(out, ".ckpt", proof=older_export)  # --overwrite replaces only a file gpc wrote
    try:
        kind = detect_format(path)
    except DataError:
        kind = GPC  # not a policy of any format: read_checkpoint names what is wrong
    if kind != GPC:  # a foreign policy needs no export: gpc eval reads it as it is
        what = {LEROBOT: "a LeRobot policy", DIFFUSION_POLICY: "a Diffusion Policy checkpoint"}[kind]
        raise DataError(f"{path}: is {what}, not a gpc checkpoint; gpc export slims gpc's own checkpoints "
                        f"(gpc eval, plan and record read {path} as it is)")
    if out.exists() and out.resolve() == path.resolve():
        raise DataError(f"{out}: is the checkpoint being exported; --out names a new file")
    if out.exists() and not overwrite:
        raise DataError(f"{out}: already exists; choose another --out or pass --overwrite")
    ckpt = read_checkpoint(path, None)
    if "state_dict" not in ckpt:  # a checkpoint of checkpoints (gpc ensemble's): nothing of its own to slim
        raise DataError(f"{path}: a {ckpt['gpc'].get('kind')!r} checkpoint holds no network of its own to export "
                        "(gpc ensemble --half writes its members slim)")
    adopt([out], older_export)
    buffer = io.BytesIO()
    torch.save(for_planning(ckpt, half), buffer)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(out, buffer.getvalue())
    typer.echo(f"wrote {out}: {ckpt['gpc']['kind']}, {len(buffer.getvalue()) / 2**20:.1f} MiB "
               f"(from {path.stat().st_size / 2**20:.1f} MiB)")


@app.command("ensemble")
def ensemble(
    members: list[Path] = typer.Argument(..., help="Two or more world-model checkpoints of one task (state or image)."),
    out: Path = typer.Option(..., "--out", "-o", help="The .ckpt file to write (a new path)."),
    pessimism: float = typer.Option(0.0, "--pessimism", help="A candidate's score is the members' mean reward less this "
                                    "many times their spread (0: the mean)."),
    half: bool = typer.Option(False, "--half", help="Store the members' network weights in float16 (as gpc export --half)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace a file already at --out."),
) -> None:
    """Several world models as one to plan with (``--world-model``): each candidate is scored by every member's
    prediction, and the scores combined, so what one model alone gets wrong counts less."""
    from gpc.datasets.errors import DataError
    from gpc.harness.files import check_file_out, write_bytes_atomic
    from gpc.models.world_models.ensemble import KIND, ensemble_checkpoint, save_ensemble

    if any(out.exists() and out.resolve() == m.resolve() for m in members):
        raise DataError(f"{out}: is one of the members; --out names a new file")
    check_file_out(out, ".ckpt")  # --overwrite replaces only a file gpc wrote
    if out.exists() and not overwrite:
        raise DataError(f"{out}: already exists; choose another --out or pass --overwrite")
    data = save_ensemble(ensemble_checkpoint(members, pessimism, half))
    out.parent.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(out, data)
    typer.echo(f"wrote {out}: {KIND} of {len(members)} members, pessimism {pessimism:g}, {len(data) / 2**20:.1f} MiB")


@app.command("eval-expert")
def eval_expert(
    seeds: str = typer.Option("100000:100100", "--seeds", help="Seed range START:STOP (stop excluded)."),
    goal: str = typer.Option("fixed", "--goal", help="fixed or random goal."),
    out: Path | None = typer.Option(None, "--out", help="Write per-seed JSON and a Markdown summary to this directory."),
    task: str = typer.Option(DEFAULT_TASK, "--task", help="Task whose expert to score."),
) -> None:
    """Score the scripted expert in closed loop (the task's episode length, max reward per episode)."""
    from gpc.cli.reports import collector_report, parse_seeds

    report = collector_report(task, "expert", parse_seeds(seeds), goal, out)
    typer.echo(report)


def main() -> None:
    import logging

    from gpc.harness.interrupts import deferred_signals
    from gpc.harness.memory import keep_freed_memory

    # Zarr writes chunks on its own event loop; after a failed write (a full disk) the chunks still pending
    # would be reported at exit as "Task was destroyed but it is pending!" below gpc's one line.
    logging.getLogger("asyncio").setLevel(logging.CRITICAL)
    keep_freed_memory()  # large tensors would otherwise fault their pages in anew each time (gpc.harness.memory)

    with deferred_signals():  # Ctrl-C and SIGTERM stop at the next safe point, with what was kept
        app()


if __name__ == "__main__":
    main()
