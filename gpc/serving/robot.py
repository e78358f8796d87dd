"""The task's simulator as the "robot" of a served controller: episodes run through ``gpc.client``.

``sync_episode`` steps exactly as ``gpc.harness.evaluation.run_group`` does (same observations, same history,
same random stream by seed), so its score equals `gpc eval`'s; ``async_episode`` runs at the task's control
rate while the next chunk is planned (``gpc.client.AsyncChunks``). A real robot replaces ``env`` by its driver.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from gpc.client import AsyncChunks, PolicyClient
from gpc.harness.episode_rows import add_step, new_row
from gpc.tasks import get_task


class SimRobot:
    """One environment of the task, observed with the keys the server reads."""

    def __init__(self, client: PolicyClient) -> None:
        meta = client.metadata
        self.task = get_task(meta["task"])
        self.keys = tuple(meta["observations"])
        self.env = self.task.make_env(meta["goal"])
        self.images, self.sim = "img" in self.keys, self.task.sim_key in self.keys

    def reset(self, seed: int) -> dict[str, np.ndarray]:
        self.env.reset(seed=seed)
        self.row: dict[str, Any] = new_row(self.task, seed)
        return self.observe()

    def observe(self) -> dict[str, np.ndarray]:
        return self.task.with_derived(self.task.observe(self.env, self.images, self.sim), self.keys)

    def final_state(self) -> list[float]:
        """The task state now, as `gpc eval` records it at an episode's end."""
        return [float(v) for v in self.task.observe(self.env, False, False)["state"]]

    def step(self, action: np.ndarray) -> bool:
        """Execute one action; True when the episode ended (success, or the task's simulation went unstable)."""
        return add_step(self.task, self.row, *self.env.step(np.asarray(action, dtype=np.float64))[1:])


def sync_episode(client: PolicyClient, seed: int, max_steps: int | None = None,
                 frames: Callable[[np.ndarray], None] | None = None) -> dict[str, Any]:
    """One episode, a decision at a time (the robot stands still while it is planned): the row `gpc eval` writes,
    plus the decisions' round trips and planning seconds."""
    robot = SimRobot(client)
    limit = max_steps or robot.task.max_episode_steps
    history = client.history(robot.reset(seed))
    client.reset(seed)
    trips, planning = [], []
    while True:
        decision = client.act(history.arrays())
        trips.append(decision.round_trip_s)
        planning.append(decision.planning_s)
        for action in decision.actions:
            if frames:
                frames(robot.env.frame(256))
            ended = robot.step(action)
            history.push(robot.observe())
            if ended or robot.row["steps"] >= limit:
                return {**robot.row, "final_state": robot.final_state(), "round_trip_s": trips, "planning_s": planning}


def async_episode(client: PolicyClient, seed: int, max_steps: int | None = None, fps: float | None = None,
                  lead: int | None = None, frames: Callable[[np.ndarray], None] | None = None) -> dict[str, Any]:
    """One episode at the control rate (``fps``, default the task's): an action every tick while the next chunk is
    planned; the robot idles only when a chunk is spent before the next arrives."""
    robot = SimRobot(client)
    rate = float(fps or robot.task.fps)
    limit = max_steps or robot.task.max_episode_steps
    runner = AsyncChunks(client, rate, lead)
    runner.start(robot.reset(seed), seed)
    late = 0  # ticks the loop overran (the simulator's own step took longer than a tick)
    t_next = time.perf_counter()
    while True:
        action = runner.next_action()
        if frames:
            frames(robot.env.frame(256))
        ended = robot.step(action)
        runner.observe(robot.observe())
        if ended or robot.row["steps"] >= limit:
            break
        t_next += 1.0 / rate
        pause = t_next - time.perf_counter()
        if pause > 0:
            time.sleep(pause)
        else:
            late += 1
            t_next = time.perf_counter()
    runner.wait_pending()
    s = runner.stats
    return {**robot.row, "final_state": robot.final_state(), "round_trip_s": s.round_trip_s, "planning_s": s.planning_s,
            "skipped": s.skipped, "idle_s": s.idle_s, "overran_ticks": late}
