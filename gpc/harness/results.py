"""A results folder that never loses a run: checked before the work, one writer, each finished group kept.

``run_into(out, recipe, config)`` is what `gpc eval` and `gpc plan` do: before any episode it checks
that ``out`` can be written and does not hold another run's results (unless ``resume`` or
``overwrite`` says so), then holds the folder's lock while each finished lockstep group is saved
(``out/.groups/``, one JSON file each, written whole) and finally ``episodes.json``,
``summary.json`` and ``summary.md``. A run stopped (SIGINT, SIGTERM, SIGKILL) is finished by the
same command with ``--resume``: the saved groups are not run again, and since every episode draws
from its own random stream the results equal an uninterrupted run's (decision times aside).

A run's identity is what its numbers depend on (``gpc.harness.identity``): the evaluation settings (not
the worker count), the controller with its sampler and reward, and the checkpoints' contents (SHA-256),
so a retrained checkpoint or another sampler is a new run.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from gpc.datasets.errors import DataError
from gpc.datasets.fresh import fresh
from gpc.datasets.locks import check_free, exclusive
from gpc.harness import interrupts
from gpc.harness.evaluation import EvalConfig, evaluate, write_results, write_spread
from gpc.harness.files import check_out, read_json, write_atomic
from gpc.harness.identity import first_difference, run_identity
from gpc.harness.ownership import RECORD, adopt, claim, remove
from gpc.harness.recipes import PlannerRecipe

GROUPS = ".groups"
RESULT_FILES = ("episodes.json", "summary.json", "summary.md")


def _held(out: Path) -> Any:
    """The identity of the run whose results ``out`` holds (finished or not), or None when it holds none."""
    for record in (out / GROUPS / "run.json", out / "summary.json"):
        if record.is_file():
            held = read_json(record)
            if not isinstance(held, dict):
                raise DataError(f"{record}: not a gpc results record (not a JSON object); move it away or choose another --out")
            return held.get("run", "unknown")
    return None


def _results_record(path: Path) -> bool:
    """An older gpc's results file (it kept no ownership record): its folder's ``summary.json`` (or the
    stopped run's ``.groups/run.json``) is a gpc results record."""
    folder = path.parent.parent if path.parent.name == GROUPS else path.parent
    for record in (folder / "summary.json", folder / GROUPS / "run.json"):
        held = read_json(record) if record.is_file() else None
        if isinstance(held, dict) and ("run" in held or {"config", "mean_score"} <= set(held)):
            return True
    return False


def _ours(out: Path) -> list[Path]:
    """The files a run writes in ``out`` (and removes when it replaces another run's)."""
    groups = out / GROUPS
    return [out / name for name in RESULT_FILES] + ([groups / "run.json", *groups.glob("group-*.json")] if groups.is_dir() else [])


def check_results(out: Path, identity: dict[str, Any], resume: bool, overwrite: bool) -> None:
    """Refuse, reading only, results ``out`` holds that this run may not touch.

    ``resume``: go on with the same run (refused for another); ``overwrite``: replace another run's
    results; both: go on if it is the same run, else replace. A folder another process is writing is refused first,
    naming its pid; a file there that gpc did not write is refused whatever the flags (``gpc.harness.ownership``).
    """
    check_free(out, "results folder")
    claim(_ours(out), proof=_results_record)
    held = _held(out)
    same = held == identity
    if held is not None and not (resume and same) and not overwrite:
        if resume:
            raise DataError(f"{out}: holds results of another run ({first_difference(held, identity)}); "
                            "--resume only finishes the same run (pass --overwrite to replace them)")
        raise DataError(f"{out}: already holds results; pass --resume to finish the same run or --overwrite to "
                        "replace them, or choose another --out")


def prepare(out: Path, identity: dict[str, Any], resume: bool, overwrite: bool) -> list[dict[str, Any]]:
    """Make ``out`` ready for this run (see ``check_results``); returns the groups an earlier, stopped run of it finished."""
    check_results(out, identity, resume, overwrite)
    adopt(_ours(out), _results_record)
    _clear_other(out, identity, resume)
    groups = out / GROUPS
    groups.mkdir(parents=True, exist_ok=True)
    write_atomic(groups / "run.json", json.dumps({"run": identity}, indent=1))
    return [read_json(p) for p in sorted(groups.glob("group-*.json"))]


def _clear_other(out: Path, identity: dict[str, Any], resume: bool) -> None:
    """Remove the results of another run (``check_results`` allowed it: --overwrite)."""
    held = _held(out)
    if held is not None and not (resume and held == identity):
        for path in _ours(out):
            remove(path)
        _drop_groups(out)


def _drop_groups(out: Path) -> None:
    """Remove the finished (or replaced) run's ``.groups`` folder: gpc's files in it, then the folder once
    nothing but gpc's record is left (a file someone put there keeps it)."""
    groups = out / GROUPS
    if not groups.is_dir():
        return
    for path in _ours(out)[len(RESULT_FILES):]:
        remove(path)
    if all(p.name == RECORD or _temporary(p) for p in groups.iterdir()):
        shutil.rmtree(groups)


def _temporary(path: Path) -> bool:
    """A file gpc's writes leave only when killed mid-write (``ownership.temporary_beside``)."""
    return path.name.startswith(".") and path.name.endswith(".tmp")


def run_into(out: Path, recipe: PlannerRecipe, config: EvalConfig, resume: bool = False, overwrite: bool = False,
             on_group: Any = None) -> dict[str, Any]:
    """Evaluate ``recipe`` on ``config``'s seeds into ``out``; returns the result (``write_results`` wrote it)."""
    out = Path(out)
    check_out(out)
    identity = run_identity(recipe, config)
    check_results(out, identity, resume, overwrite)
    with exclusive(out, "results folder"):
        if resume and (out / "summary.json").is_file() and _held(out) == identity and not (out / GROUPS).exists():
            return {**read_json(out / "summary.json"), "episodes": read_json(out / "episodes.json")}
        with fresh(out) as made, fresh(out / GROUPS) as made_groups:  # a failed start leaves neither behind
            finished = prepare(out, identity, resume, overwrite)

            def keep(group: dict[str, Any]) -> None:
                write_atomic(out / GROUPS / f"group-{group['episodes'][0]['seed']:012d}.json", json.dumps(group))
                made.keep()
                made_groups.keep()
                if on_group:
                    on_group(group)

            try:
                result = evaluate(recipe, config, on_group=keep, finished=finished)
            except interrupts.Interrupted as stop:
                done = len(list((out / GROUPS).glob("group-*.json")))
                stop.kept = (f"{done} of {len(config.groups())} lockstep groups are kept in {out / GROUPS} "
                             "(run the same command with --resume to finish)")
                raise
        result["controller"] = recipe.summary()
        result["run"] = identity
        write_results(result, out, f"{recipe.label}: {recipe.policy}")
        _drop_groups(out)
    return result


def _runs(out: Path, recipe: PlannerRecipe, config: EvalConfig,
          sampling_seeds: Sequence[int]) -> list[tuple[Path, EvalConfig, dict[str, Any]]]:
    """(folder, config, identity) of each sampling seed's run (videos for the first only)."""
    if len(sampling_seeds) == 1:
        one = dataclasses.replace(config, sampling_seed=sampling_seeds[0])
        return [(out, one, run_identity(recipe, one))]
    twice = sorted({s for s in sampling_seeds if list(sampling_seeds).count(s) > 1})
    if twice:
        raise ValueError(f"--sampling-seeds: {', '.join(map(str, twice))} given twice")
    runs = []
    for i, s in enumerate(sampling_seeds):
        one = dataclasses.replace(config, sampling_seed=s)
        if i:
            one = dataclasses.replace(one, videos=0, video_dir=None)
        runs.append((out / f"sampling-seed-{s}", one, run_identity(recipe, one)))
    return runs


def check_eval(out: Path, recipe: PlannerRecipe, config: EvalConfig, sampling_seeds: Sequence[int] = (0,),
               resume: bool = False, overwrite: bool = False) -> None:
    """Refuse, reading only and before any episode, what ``run_eval`` with these arguments may not write."""
    out = Path(out)
    check_out(out)
    runs = _runs(out, recipe, config, sampling_seeds)
    if len(runs) > 1:
        check_results(out, {"sampling_seeds": list(sampling_seeds), "runs": [r[2] for r in runs]}, resume, overwrite)
    for folder, _, identity in runs:
        check_out(folder)
        check_results(folder, identity, resume, overwrite)
    if config.videos and config.video_dir:
        check_out(Path(config.video_dir))
        claim([Path(config.video_dir) / f"seed{s}.mp4" for s in config.seeds[: config.videos]])


def run_eval(out: Path, recipe: PlannerRecipe, config: EvalConfig, sampling_seeds: Sequence[int] = (0,),
             resume: bool = False, overwrite: bool = False, on_group: Any = None) -> dict[str, Any]:
    """`gpc eval`: ``config`` once per sampling seed (videos for the first only); with several, each run has its
    own folder ``out/sampling-seed-S`` and ``out/summary.*`` holds the spread of their scores.

    Every folder is checked before the first episode runs (``check_eval``); the spread is a run of
    its own, whose identity is the sampling seeds and what each run's numbers depend on.
    """
    out = Path(out)
    check_eval(out, recipe, config, sampling_seeds, resume, overwrite)
    runs = _runs(out, recipe, config, sampling_seeds)
    if len(runs) == 1:
        return run_into(out, recipe, runs[0][1], resume, overwrite, on_group)
    spread = {"sampling_seeds": list(sampling_seeds), "runs": [identity for _, _, identity in runs]}
    with exclusive(out, "results folder"), fresh(out) as made:
        _clear_other(out, spread, resume)

        def kept(group: dict[str, Any]) -> None:
            made.keep()  # the first finished group of any seed's run is a result
            if on_group:
                on_group(group)

        results = [run_into(folder, recipe, one, resume, overwrite, kept) for folder, one, _ in runs]
        return write_spread(results, out, f"{recipe.label}: {recipe.policy}", spread)
