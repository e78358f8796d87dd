"""`gpc serve`: a controller served over a WebSocket to a robot's computer (``gpc.serving``, client ``gpc.client``)."""

from __future__ import annotations

import typer

from gpc.cli.eval_cmd import Checkpoint, Goal, PlannerKind, Threads, recipe_from_options, with_planning_options


@with_planning_options
def serve(
    checkpoint: Checkpoint,
    planner: PlannerKind = "bc",
    planning: dict | None = None,
    host: str = typer.Option("127.0.0.1", "--host", help="Address to listen on; the default answers this machine only (0.0.0.0: every interface, with --token)."),
    port: int = typer.Option(8765, "--port", min=0, max=65535, help="TCP port (0: any free one, printed)."),
    token: str | None = typer.Option(None, "--token", envvar="GPC_TOKEN", show_envvar=True, help="Shared secret a client's hello must carry."),
    sampling_seed: int = typer.Option(0, "--sampling-seed", min=0, help="With each episode's seed, seeds its random stream (as gpc eval --sampling-seeds)."),
    max_message_mb: float | None = typer.Option(None, "--max-message-mb", min=0.001, help="Largest message accepted, in MiB (default: 4x a float64 request, at least 1)."),
    goal: Goal = "fixed",
    threads: Threads = 1,
) -> None:
    """Serve BC or a planner: clients send observation histories, the server answers action chunks (Ctrl-C stops)."""
    from gpc.serving.server import ServeConfig, serve_recipe

    assert planning is not None  # with_planning_options passes them
    if token is not None and not token:
        raise ValueError("--token: empty; give a secret or leave the option out")
    recipe = recipe_from_options(checkpoint, planner, planning, goal)
    size = int(max_message_mb * 2**20) if max_message_mb else None
    config = ServeConfig(host=host, port=port, token=token, goal=goal, sampling_seed=sampling_seed, threads=threads, max_size=size)
    serve_recipe(recipe, config, announce=typer.echo)


def register(app: typer.Typer) -> None:
    app.command("serve")(serve)
