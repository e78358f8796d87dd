"""`gpc eval` (closed loop: BC or a planner), `gpc plan` (one seed, the futures drawn) and `gpc compare`."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from gpc.cli.backend import backend_from_options, cluster_bar, with_backend_options
from gpc.cli.groups import DefaultToRun
from gpc.cli.limits import MAX_COUNT, MAX_PROCESSES, MAX_SEED
from gpc.cli.run_options import with_shared_options

eval_app = typer.Typer(
    cls=DefaultToRun, no_args_is_help=True,
    help="Evaluate: `gpc eval CKPT` runs the policy (or --planner) in closed loop; `gpc eval world-model CKPT` scores predictions.",
)

Checkpoint = Annotated[Path, typer.Argument(help="Policy: a gpc checkpoint, a LeRobot policy directory or a Diffusion Policy .ckpt.")]
PlannerKind = Annotated[str, typer.Option("--planner", help="bc (the policy alone), rank, opt, rank-opt, gt-sim, cem, mppi, grad; the baselines vgps, dreamer, ladi (--world-model: their checkpoint); or one registered by name.")]
WorldModel = Annotated[str | None, typer.Option("--world-model", help="World-model checkpoint (gt-sim: the true simulator).")]
K = Annotated[int | None, typer.Option("--K", "-K", help="Proposals (rank, rank-opt), random chunks (grad) or samples per iteration (cem, mppi); default 100, opt 1.")]
M = Annotated[int | None, typer.Option("--M", "-M", help="Gradient steps (opt, rank-opt, grad) or iterations (cem, mppi); default 30 (cem, mppi: 5).")]
Lr = Annotated[float | None, typer.Option("--lr", help="Gradient planners: Adam step size on the actions, in action units (default: 1/256 of the task's action range: 2 px on the planar tasks, 1.6 mm on Block Stacking).")]
LrDecay = Annotated[str, typer.Option("--lr-decay", help="Step size over the M steps: constant or cosine (to 0).")]
TrustRegion = Annotated[float, typer.Option("--trust-region", help="Gradient planners: how far (action units: px, or m on Block Stacking) an action may move from its proposal; 0: no limit.")]
Knots = Annotated[int, typer.Option("--knots", min=0, max=MAX_COUNT, help="Gradient planners: ascend N offsets linearly interpolated over the chunk (it bends smoothly); 0: every action.")]
KeepBest = Annotated[bool, typer.Option("--keep-best", help="Gradient planners: end at each candidate's best-scoring iterate (the proposal included), not the last.")]
Reward = Annotated[str, typer.Option("--reward", help="registration (state futures), learned (image futures) or vlm.")]
RewardAggregate = Annotated[str, typer.Option("--reward-aggregate", help="final: the last predicted step; discounted: a discounted sum.")]
RewardCkpt = Annotated[str | None, typer.Option("--reward-checkpoint", help="--reward learned: the reward checkpoint.")]
VlmUrl = Annotated[str | None, typer.Option("--vlm-base-url", help="--reward vlm: an OpenAI-compatible endpoint, e.g. http://localhost:8000/v1.")]
VlmModel = Annotated[str | None, typer.Option("--vlm-model", help="--reward vlm: the model name the endpoint serves.")]
Method = Annotated[str | None, typer.Option("--method", help="ddim or ddpm (default: the checkpoint's).")]
Steps = Annotated[int | None, typer.Option("--steps", min=1, max=MAX_COUNT, help="Denoising steps (default: the checkpoint's).")]
Device = Annotated[str, typer.Option("--device", help="Where the policy, world model and reward run: cpu or cuda (with --backend ray: on the workers).")]
RolloutPrecision = Annotated[str, typer.Option("--precision", help="The world model's rollouts: bf16-auto (bf16 where the model asks for it and the hardware computes it), 32-true (float32 on every machine: the same numbers) or bf16-mixed.")]
ActionSteps = Annotated[int | None, typer.Option("--action-steps", min=1, max=MAX_COUNT, help="Planners: actions executed per decision (default: the policy's n_action_steps; at most the chunk the planner scores).")]
PolicyFormat = Annotated[str | None, typer.Option("--policy-format", help="gpc, lerobot or diffusion_policy (default: detected).")]
PolicyTask = Annotated[str | None, typer.Option("--task", help="Task a LeRobot or Diffusion Policy checkpoint acts in (default: pusht; a gpc checkpoint names its own).")]
Spacing = Annotated[str | None, typer.Option("--spacing", help="Steps a short chain visits: leading (Diffusion Policy's) or trailing (starts from pure noise).")]
Goal = Annotated[str, typer.Option("--goal", help="fixed or random goal.")]
MaxSteps = Annotated[int | None, typer.Option("--max-steps", min=1, max=MAX_COUNT, help="Steps per episode at most (default: the task's episode length).")]
Threads = Annotated[int, typer.Option("--threads", min=1, max=MAX_PROCESSES, help="Torch threads per process (part of what makes runs repeatable).")]
Resume = Annotated[bool, typer.Option("--resume", help="Finish the run this --out holds (its saved groups are not run again).")]
Overwrite = Annotated[bool, typer.Option("--overwrite", help="Replace the results this --out holds (with --resume: only if they are another run's).")]

# What every closed-loop command takes to build its controller (received as ``planning``).
PLANNING_OPTIONS = (
    ("world_model", WorldModel, None), ("k", K, None), ("m", M, None), ("lr", Lr, None), ("lr_decay", LrDecay, "constant"),
    ("trust_region", TrustRegion, 0.0), ("keep_best", KeepBest, False), ("knots", Knots, 0), ("reward", Reward, "registration"),
    ("reward_aggregate", RewardAggregate, "final"), ("reward_checkpoint", RewardCkpt, None),
    ("vlm_base_url", VlmUrl, None), ("vlm_model", VlmModel, None), ("method", Method, None), ("steps", Steps, None),
    ("spacing", Spacing, None), ("policy_format", PolicyFormat, None), ("task", PolicyTask, None),
    ("action_steps", ActionSteps, None), ("precision", RolloutPrecision, "bf16-auto"), ("device", Device, "cpu"),
)
with_planning_options = with_shared_options(PLANNING_OPTIONS, "planning")


def recipe_from_options(checkpoint: Path, planner: str, planning: dict, goal: str, keep_futures: bool = False,
                        vlm_cache: Path | None = None, remote: bool = False):
    """The controller recipe the options describe (``gpc.harness.recipes.make_recipe``); ``remote``: it runs on
    Ray workers, whose GPUs this machine need not have."""
    from gpc.harness.recipes import ASCENT_DEFAULTS, RewardSpec, make_recipe
    from gpc.models.planning.config import SamplingConfig

    o = planning
    if o["device"] == "cuda" and not remote:
        import torch

        if not torch.cuda.is_available():
            raise ValueError("--device cuda: torch sees no CUDA GPU on this machine (use --device cpu, or --backend ray with GPU workers)")
    vlm = None
    if o["reward"] == "vlm":
        from gpc.models.rewards.vlm import VLMConfig

        if not o["vlm_base_url"] or not o["vlm_model"]:
            raise ValueError("--reward vlm needs --vlm-base-url and --vlm-model (the key comes from $OPENAI_API_KEY)")
        vlm = VLMConfig(base_url=o["vlm_base_url"], model=o["vlm_model"], cache_dir=str(vlm_cache) if vlm_cache else None)
    ascent = {key: o[key] for key in ASCENT_DEFAULTS}  # the gradient planners' guards, named once in recipes
    return make_recipe(checkpoint, planner, world_model=o["world_model"], k=o["k"], m=o["m"], lr=o["lr"], ascent=ascent,
                       reward=RewardSpec(o["reward"], o["reward_aggregate"], o["reward_checkpoint"], vlm),
                       sampling=SamplingConfig(o["method"], o["steps"], o["spacing"]), goal=goal,
                       keep_futures=keep_futures, task=o["task"], policy_format=o["policy_format"],
                       action_steps=o["action_steps"], precision=o["precision"], device=o["device"])


@eval_app.command("run")
@with_backend_options
@with_planning_options
def eval_run(
    checkpoint: Checkpoint,
    planner: PlannerKind = "bc",
    planning: dict | None = None,
    scale: dict | None = None,
    seeds: str = typer.Option("100000:100050", "--seeds", help="Seed range START:STOP (stop excluded) or a list."),
    out: Path = typer.Option(Path("results/eval"), "--out", "-o", help="Directory for episodes.json, summary.json, summary.md, videos."),
    sampling_seeds: str = typer.Option("0", "--sampling-seeds", help="Sampling seed(s), e.g. 0,1,2: each seeds every episode's random stream (with its env seed); several give the spread."),
    workers: int = typer.Option(1, "--workers", "-j", min=1, max=MAX_PROCESSES, help="Processes (Ray workers with --backend ray); results are identical for any count."),
    batch: int = typer.Option(25, "--batch", min=1, max=MAX_COUNT, help="Episodes stepped in lockstep per controller call."),
    threads: Threads = 1,
    goal: Goal = "fixed",
    max_steps: MaxSteps = None,
    videos: int = typer.Option(0, "--videos", min=0, max=MAX_COUNT, help="Write MP4s (planned chunk and, for planners, the predicted futures) for the first N seeds."),
    resume: Resume = False,
    overwrite: Overwrite = False,
) -> None:
    """Closed-loop evaluation of the frozen policy (BC) or a planner over it, on test seeds."""
    from rich.progress import Progress

    from gpc.cli.reports import parse_seeds
    from gpc.harness.evaluation import EvalConfig
    from gpc.harness.results import check_eval, check_out, run_eval

    assert planning is not None  # with_planning_options passes them
    backend = backend_from_options(scale, planning["device"])
    check_out(out)
    samplings, test_seeds = parse_seeds(sampling_seeds, "--sampling-seeds"), tuple(parse_seeds(seeds))
    recipe = recipe_from_options(checkpoint, planner, planning, goal, keep_futures=videos > 0, vlm_cache=out / "vlm_cache",
                                 remote=backend is not None)
    config = EvalConfig(seeds=test_seeds, task=recipe.task, goal=goal, max_steps=max_steps, batch=batch, workers=workers,
                        threads=threads, video_dir=str(out / "videos") if videos else None, videos=videos, backend=backend)
    check_eval(out, recipe, config, samplings, resume, overwrite)  # before the bar: a refusal prints one line
    if backend is not None:
        with cluster_bar(recipe.label, len(test_seeds) * len(samplings)) as advance:
            run_eval(out, recipe, config, samplings, resume, overwrite, on_group=advance)
        typer.echo((out / "summary.md").read_text())
        return
    with Progress() as bar:
        tid = bar.add_task(recipe.label, total=len(test_seeds) * len(samplings))
        run_eval(out, recipe, config, samplings, resume, overwrite, on_group=lambda g: bar.advance(tid, len(g["episodes"])))
    typer.echo((out / "summary.md").read_text())


@with_planning_options
def plan_one(
    checkpoint: Checkpoint,
    planner: PlannerKind = "rank",
    planning: dict | None = None,
    seed: int = typer.Option(100000, "--seed", min=0, max=MAX_SEED, help="Environment seed."),
    out: Path = typer.Option(Path("results/plan"), "--out", "-o", help="Directory for the MP4 and the episode's JSON."),
    goal: Goal = "fixed",
    max_steps: MaxSteps = None,
    threads: Threads = 2,
    resume: Resume = False,
    overwrite: Overwrite = False,
) -> None:
    """Run one planner on one seed; the MP4 shows, per decision, the K predicted futures and their rewards."""
    from gpc.harness.evaluation import EvalConfig
    from gpc.harness.ownership import claim
    from gpc.harness.results import check_out, run_into

    if planner == "bc":
        raise typer.BadParameter("gpc plan shows a planner's futures; use `gpc eval CKPT --videos 1` for BC", param_hint="--planner")
    assert planning is not None  # with_planning_options passes them
    check_out(out)
    claim([out / f"seed{seed}.mp4"])  # the video too, before any model loads or an earlier run's results are replaced
    recipe = recipe_from_options(checkpoint, planner, planning, goal, keep_futures=True, vlm_cache=out / "vlm_cache")
    config = EvalConfig(seeds=(seed,), task=recipe.task, goal=goal, max_steps=max_steps, batch=1, threads=threads,
                        video_dir=str(out), videos=1)
    result = run_into(out, recipe, config, resume, overwrite)
    row = result["episodes"][0]
    typer.echo(f"seed {seed}: score {row['score']:.3f}, success {row['success']}, {row['steps']} steps; "
               f"wrote {out / f'seed{seed}.mp4'} and {out / 'summary.md'}")


@eval_app.command("ascent")
@with_planning_options
def eval_ascent(
    checkpoint: Checkpoint,
    planner: PlannerKind = "opt",
    planning: dict | None = None,
    seeds: str = typer.Option("200000:200010", "--seeds", help="Seed range START:STOP or a list (validation seeds: not the test seeds)."),
    out: Path = typer.Option(Path("results/ascent.md"), "--out", "-o", help="Markdown report to write (and .json beside it)."),
    batch: int = typer.Option(10, "--batch", min=1, max=MAX_COUNT, help="Episodes stepped in lockstep per planner call."),
    threads: Threads = 1,
    goal: Goal = "fixed",
    max_steps: int = typer.Option(48, "--max-steps", min=1, max=MAX_COUNT, help="Steps per episode (every decision is probed)."),
) -> None:
    """Why GPC-OPT helps or not: every ascent iterate scored by the planner and replayed in the true simulator."""
    import json

    from gpc.cli.reports import parse_seeds
    from gpc.harness.files import check_file_out, write_atomic
    from gpc.harness.opt_probe import markdown, probe, summarize

    assert planning is not None  # with_planning_options passes them
    check_file_out(out, ".md", beside=(".json",))
    recipe = recipe_from_options(checkpoint, planner, planning, goal)
    if recipe.planner is None or not recipe.planner.uses_gradients:
        raise typer.BadParameter(f"{planner} takes no gradient steps; probe opt, rank-opt or grad", param_hint="--planner")
    controller = recipe()
    assert recipe.task is not None  # make_recipe names the task
    episodes, decisions = probe(controller, recipe.task, tuple(parse_seeds(seeds)), max_steps, batch, goal, threads)
    summary = {"controller": recipe.summary(), "seeds": seeds, "max_steps": max_steps, **summarize(decisions), **episodes}
    report = markdown(summary, f"Gradient ascent probed: {recipe.label}, seeds {seeds}, {max_steps} steps")
    out.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(out.with_suffix(".json"), json.dumps(summary, indent=1))
    write_atomic(out, report)
    typer.echo(report)
    typer.echo(f"wrote {out} and {out.with_suffix('.json')}")


@eval_app.command("ranking")
@with_planning_options
def eval_ranking(
    checkpoint: Checkpoint,
    planner: PlannerKind = "rank",
    planning: dict | None = None,
    scorer: list[str] = typer.Option([], "--scorer", help="PLANNER=CHECKPOINT, repeated: each ranking planner to probe "
                                     "(rank=WM.ckpt, vgps=VALUE.ckpt, dreamer=LATENT.ckpt, ladi=LADI.ckpt); the other options apply to all."),
    save_replays: Path | None = typer.Option(None, "--save-replays", help="A new store: every decision's K proposals "
                                             "replayed in the simulator, as short episodes a state world model trains on "
                                             "(use training seeds, not validation or test seeds)."),
    seeds: str = typer.Option("200000:200010", "--seeds", help="Seed range START:STOP or a list (validation seeds: not the test seeds)."),
    out: Path = typer.Option(Path("results/ranking.md"), "--out", "-o", help="Markdown report to write (and .json beside it)."),
    batch: int = typer.Option(10, "--batch", min=1, max=MAX_COUNT, help="Episodes stepped in lockstep."),
    goal: Goal = "fixed",
    max_steps: int = typer.Option(300, "--max-steps", min=1, max=MAX_COUNT, help="Steps per episode (every decision is probed)."),
) -> None:
    """How well each scorer orders the policy's K proposals, against the true simulator on the same chunks (BC's states)."""
    import json

    from gpc.cli.reports import parse_seeds
    from gpc.harness.files import check_file_out, write_atomic
    from gpc.harness.ownership import digest_file
    from gpc.harness.rank_probe import markdown, probe_ranking
    from gpc.harness.replays import ReplayLog, check_replay_out
    from gpc.tasks import get_task

    assert planning is not None  # with_planning_options passes them
    check_file_out(out, ".md", beside=(".json",))
    if not scorer and save_replays is None:
        raise typer.BadParameter("name a scorer to probe (rank=WM.ckpt), or --save-replays STORE", param_hint="--scorer")
    if save_replays is not None:
        check_replay_out(save_replays)
    pairs = [s.partition("=") for s in scorer]
    if any(not name or not sep or not ckpt for name, sep, ckpt in pairs):
        raise typer.BadParameter("use PLANNER=CHECKPOINT (rank=runs/wm/checkpoints/last.ckpt)", param_hint="--scorer")
    names = [name for name, _, _ in pairs]
    planners, recipes, task_name = {}, [], None
    for name, _, ckpt in pairs:
        recipe = recipe_from_options(checkpoint, name, {**planning, "world_model": ckpt}, goal)
        kind = recipe.planner.planner if recipe.planner is not None else None
        if kind is None or kind.uses_gradients or kind.iterates or not kind.uses_policy:
            raise typer.BadParameter(f"{name}: probe planners that rank the policy's proposals once (rank, vgps, dreamer, ladi)",
                                     param_hint="--scorer")
        planners[name if names.count(name) == 1 else f"{name} {ckpt}"] = recipe()
        recipes.append(recipe.summary())
        task_name = recipe.task
    proposer = recipe_from_options(checkpoint, "gt-sim", planning, goal) if not pairs else None  # the policy alone proposes
    task_name = proposer.task if proposer is not None else task_name
    assert task_name is not None  # make_recipe names the task
    task = get_task(task_name)
    k = planning["k"] or 100
    first = proposer() if proposer is not None else None
    replays = ReplayLog.for_proposer(first or next(iter(planners.values()))) if save_replays else None
    if replays is not None:  # a replay needs history - 1 executed actions before its decision: refused before the work
        act = (first or next(iter(planners.values()))).n_action_steps
        need = -(-(replays.history - 1) // act) * act  # the step of the first decision that has them
        if need >= (max_steps or task.max_episode_steps):
            raise typer.BadParameter(f"{max_steps}: --save-replays keeps decisions with {replays.history - 1} executed "
                                     f"actions before them, the first at step {need}; raise it above {need}", param_hint="--max-steps")
    summary = {"scorers_run": recipes, "seeds": seeds, "k": k, "max_steps": max_steps,
               **probe_ranking(planners, task, tuple(parse_seeds(seeds)), k, max_steps, batch, goal, first, replays)}
    report = markdown(summary, f"Ranking probed: {', '.join(planners) or 'no scorer'}, K={k}, seeds {seeds}, {max_steps} steps")
    if replays is not None and save_replays is not None:  # the policy's weights by content, as `gpc record` names them
        made_by = {"policy": str(checkpoint), "checkpoints": {str(checkpoint): digest_file(Path(checkpoint))}
                   if Path(checkpoint).is_file() else {}}  # (a LeRobot policy directory is named by path alone)
        n = replays.write(save_replays, task, {**made_by, "k": k, "seeds": seeds, "max_steps": max_steps, "goal": goal,
                                                "history": replays.history})
        summary["replays"] = {"store": str(save_replays), "episodes": n}
    out.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(out.with_suffix(".json"), json.dumps(summary, indent=1))
    write_atomic(out, report)
    typer.echo(report)
    if "replays" in summary:
        typer.echo(f"wrote {summary['replays']['episodes']} replayed proposals to {save_replays}")
    typer.echo(f"wrote {out} and {out.with_suffix('.json')}")


def compare(
    runs: list[Path] = typer.Argument(..., help="Result directories of `gpc eval` (same seeds); A+B joins one controller's runs on two seed ranges."),
    baseline: Path = typer.Option(..., "--baseline", help="The BC result directory the others are paired with."),
    ceiling: Path | None = typer.Option(None, "--ceiling", help="The gt-sim result: report the share of the BC-to-ceiling gap closed."),
    out: Path = typer.Option(Path("results/compare.md"), "--out", "-o", help="Markdown table to write (and .json beside it)."),
    title: str = typer.Option("Planners against BC (paired over seeds)", "--title"),
    paper: str | None = typer.Option(None, "--paper", help="Paper figures to show beside ours: a task name (pusht-state)."),
    seeds: str | None = typer.Option(None, "--seeds", help="START:STOP: pair on these seeds alone (every run must hold them)."),
) -> None:
    """Paired comparison of planners against BC: mean difference with a 95% CI, gap to the ceiling closed."""
    from gpc.cli.reports import parse_seeds
    from gpc.datasets.locks import exclusive
    from gpc.harness import interrupts
    from gpc.harness.comparison import adopt_older, check_compare_out, compare_runs, render_plot, write_comparison
    from gpc.harness.files import write_bytes_atomic

    check_compare_out(out)
    table = compare_runs(baseline, runs, ceiling, parse_seeds(seeds) if seeds else None)  # every input read and checked before anything is written
    plot = out.with_suffix(".png")
    png = render_plot(table, plot)
    interrupts.check()
    with exclusive(out, "comparison"):
        check_compare_out(out)
        adopt_older(out)
        md = write_comparison(table, out, title, paper)
        write_bytes_atomic(plot, png)
    typer.echo(md)
    typer.echo(f"wrote {out}, {out.with_suffix('.json')} and {plot}")


def register(app: typer.Typer) -> None:
    """Wire `gpc eval`, `gpc plan` and `gpc compare` into the root CLI."""
    app.add_typer(eval_app, name="eval")
    app.command("plan")(plan_one)
    app.command("compare")(compare)
