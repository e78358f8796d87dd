"""The robot-side client of `gpc serve`: numpy, websockets and msgpack only (no torch on the robot's computer).

Three lines on the robot::

    client = PolicyClient("ws://gpu-box:8765", token=os.environ.get("GPC_TOKEN"))
    history = client.history(first_observation)          # the last n_obs_steps observations, as the server wants them
    decision = client.act(history.arrays())              # decision.actions: the chunk's head, to execute now

``AsyncChunks`` runs the robot at its control rate while the next decision is planned: it keeps executing the
current chunk, sends a fresh observation history ahead of time, and switches to the new chunk at the step it was
planned for (the new chunk's first actions, which the robot already passed while it was planned, are skipped).
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from websockets.sync.client import connect

from gpc.serving import wire


class ServerError(RuntimeError):
    """The server refused a request or the connection (its one-line reason)."""


@dataclass(frozen=True)
class Decision:
    """One answer: the chunk from the observation's step on, how many of its actions to execute, and the times."""

    chunk: np.ndarray  # (chunk_length, action_dim)
    action_steps: int  # the head of the chunk a synchronous loop executes before the next decision
    planning_s: float  # the server's planning time
    round_trip_s: float  # what the client measured, from sending the request to the decoded reply
    request_bytes: int
    reply_bytes: int
    episode: int
    decision: int

    @property
    def actions(self) -> np.ndarray:
        return self.chunk[: self.action_steps]

    @property
    def wire_s(self) -> float:
        """The round trip beyond planning: serialisation, transfer and the server's checks."""
        return self.round_trip_s - self.planning_s


class History:
    """The last ``n`` observations per key, oldest first; starts with the first observation repeated (as `gpc eval`)."""

    def __init__(self, keys: list[str], n: int, first: Mapping[str, Any]) -> None:
        self.keys, self.n = keys, n
        self.steps: deque[dict[str, np.ndarray]] = deque([self._pick(first)] * n, maxlen=n)

    def _pick(self, obs: Mapping[str, Any]) -> dict[str, np.ndarray]:
        missing = [k for k in self.keys if k not in obs]
        if missing:
            raise KeyError(f"observation lacks {missing} (the server reads {self.keys})")
        return {k: np.array(obs[k]) for k in self.keys}

    def push(self, obs: Mapping[str, Any]) -> None:
        self.steps.append(self._pick(obs))

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: np.stack([s[k] for s in self.steps]) for k in self.keys}


class PolicyClient:
    """One connection to `gpc serve`: the hello (and token), the server's metadata, and synchronous ``act`` calls."""

    def __init__(self, uri: str = "ws://127.0.0.1:8765", token: str | None = None, timeout: float = 30.0,
                 max_size: int = 2**26) -> None:
        self._stack = contextlib.ExitStack()  # `with connect(...)`: every websockets version's way to hold a connection
        self.ws = self._stack.enter_context(connect(uri, open_timeout=timeout, max_size=max_size, compression=None))
        try:
            self.ws.send(wire.pack({"type": "hello", "wire": wire.WIRE_VERSION, "token": token}))
            self.metadata, _ = self._receive(timeout)
            if self.metadata.get("type") != "metadata":
                raise ServerError(f"handshake: a metadata message was expected, got {self.metadata.get('type')!r}")
            if self.metadata.get("wire_version") != wire.WIRE_VERSION:
                raise ServerError(f"wire format {self.metadata.get('wire_version')}: this client speaks {wire.WIRE_VERSION}")
        except BaseException:
            self._stack.close()
            raise
        self.obs_keys: list[str] = list(self.metadata["observations"])
        self.n_obs_steps: int = int(self.metadata["n_obs_steps"])
        self.episode, self.decision, self._next_id = 0, 0, 0

    def _receive(self, timeout: float | None) -> tuple[dict[str, Any], int]:
        """The next message and its size in bytes; an error message or a close raises ``ServerError`` with the reason."""
        try:
            raw = self.ws.recv(timeout)
            message = wire.unpack(raw)
        except wire.WireError as exc:
            raise ServerError(f"reply: {exc}") from None
        except Exception as exc:  # closed by the server: its reason says why
            reason = getattr(getattr(exc, "rcvd", None), "reason", "") or str(exc)
            raise ServerError(f"connection closed: {reason}") from None
        if message.get("type") == "error":
            raise ServerError(str(message.get("error")))
        return message, len(raw)

    def history(self, first: Mapping[str, Any]) -> History:
        """An observation history of the length the server reads, filled with ``first``."""
        return History(self.obs_keys, self.n_obs_steps, first)

    def reset(self, episode: int = 0) -> None:
        """Start an episode: its seed names its random stream (the same as `gpc eval`'s for that seed)."""
        self.episode, self.decision = int(episode), 0

    def act(self, obs_history: Mapping[str, np.ndarray], timeout: float | None = None) -> Decision:
        """Plan from ``{key: (n_obs_steps, ...)}`` (oldest first); the decision's chunk starts at the newest step."""
        self._next_id += 1
        request = wire.pack({"type": "act", "id": self._next_id, "episode": self.episode, "decision": self.decision,
                             "obs": {k: np.asarray(v) for k, v in obs_history.items()}})
        t0 = time.perf_counter()
        self.ws.send(request)
        reply, size = self._receive(timeout)
        t1 = time.perf_counter()
        if reply.get("id") != self._next_id:
            raise ServerError(f"reply to request {reply.get('id')}; expected {self._next_id}")
        self.decision += 1
        return Decision(np.asarray(reply["chunk"]), int(reply["action_steps"]), float(reply["planning_s"]), t1 - t0,
                        len(request), size, self.episode, int(reply["decision"]))

    def close(self) -> None:
        self._stack.close()

    def __enter__(self) -> PolicyClient:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


@dataclass
class AsyncStats:
    """What an asynchronous episode measured: per decision, its round trip, the steps it came late, the robot's idle time."""

    round_trip_s: list[float] = field(default_factory=list)
    planning_s: list[float] = field(default_factory=list)
    skipped: list[int] = field(default_factory=list)  # the new chunk's first actions the robot had passed
    idle_s: list[float] = field(default_factory=list)  # the robot waited this long for the chunk (0 when it came in time)


class AsyncChunks:
    """Executes the current chunk while the next one is planned, switching at the step the new one was planned for.

    Call ``start(first_obs, episode)`` (one synchronous decision), then each control step ``next_action()``
    and ``observe(obs)`` with the observation the action led to. The next request goes out ``lead`` steps
    before the current chunk's executed head ends (default: the measured round trip in steps, rounded up),
    so it arrives when the head is done. When it is late the robot goes on with the current chunk's tail, up to
    the step where the coming chunk would keep fewer than ``action_steps`` actions; only there does it wait. So a
    decision slower than a chunk costs the robot the decision's time minus the ``chunk_length - action_steps``
    steps it moved meanwhile, never a second decision.
    """

    def __init__(self, client: PolicyClient, fps: float | None = None, lead: int | None = None) -> None:
        self.client = client
        self.fps = float(fps or client.metadata["fps"])
        self.fixed_lead = lead
        self.stats = AsyncStats()
        self._pending: threading.Thread | None = None
        self._reply: tuple[Decision | None, BaseException | None, int] | None = None
        self._reply_at: int | None = None  # the step the chunk in flight is planned for

    def start(self, first: Mapping[str, Any], episode: int = 0) -> None:
        self.wait_pending()
        self.client.reset(episode)
        self.history = self.client.history(first)
        self.step, self.chunk_step = 0, 0
        self.current = self.client.act(self.history.arrays())
        self._record(self.current, 0, 0.0)

    def _record(self, d: Decision, skipped: int, idle: float) -> None:
        self.stats.round_trip_s.append(d.round_trip_s)
        self.stats.planning_s.append(d.planning_s)
        self.stats.skipped.append(skipped)
        self.stats.idle_s.append(idle)

    @property
    def lead(self) -> int:
        if self.fixed_lead is not None:
            return self.fixed_lead
        return math.ceil(max(self.stats.round_trip_s[-3:]) * self.fps)

    def _request(self, at: int) -> None:
        arrays = self.history.arrays()

        def work() -> None:
            try:
                self._reply = (self.client.act(arrays), None, at)
            except BaseException as exc:  # handed to the control loop
                self._reply = (None, exc, at)

        self._reply, self._reply_at = None, at
        self._pending = threading.Thread(target=work, daemon=True)
        self._pending.start()

    def _switch(self, idle: float) -> None:
        assert self._pending is not None and self._reply is not None
        self._pending, self._reply_at = None, None
        decision, exc, at = self._reply
        if exc is not None:
            raise exc
        assert decision is not None
        self.current, self.chunk_step = decision, at
        self._record(decision, self.step - at, idle)

    def _await(self) -> None:
        t0 = time.perf_counter()
        self.wait_pending(keep=True)
        self._switch(time.perf_counter() - t0)

    def wait_pending(self, keep: bool = False) -> None:
        """Wait for the decision in flight (``keep``: to switch to it; else it is dropped)."""
        if self._pending is not None:
            self._pending.join()
            if not keep:
                self._pending, self._reply_at = None, None

    def _hold(self) -> int:
        """The index of the current chunk at which the robot waits for the chunk in flight: where that chunk, planned
        for the step it was requested at, would have fewer than ``action_steps`` actions left (at most the chunk's end)."""
        length = len(self.current.chunk)
        if self._reply_at is None:
            return length
        return min(length, self._reply_at - self.chunk_step + length - self.current.action_steps)

    def observe(self, obs: Mapping[str, Any]) -> None:
        """The observation after the last action (the next request plans from it)."""
        self.history.push(obs)

    def next_action(self) -> np.ndarray:
        """The action for this control step, from the chunk planned for the latest step it covers."""
        if self._pending is not None and not self._pending.is_alive():
            self._switch(0.0)
        index = self.step - self.chunk_step
        if self._pending is None and index >= max(0, self.current.action_steps - self.lead):
            self._request(self.step)
        if index >= self._hold():  # going on would leave the coming chunk too few actions: the robot waits for it
            self._await()
            index = self.step - self.chunk_step
        if index >= len(self.current.chunk):  # never with a server's chunk_length >= action_steps; planned anew if so
            self._request(self.step)
            self._await()
            index = 0
        self.step += 1
        return self.current.chunk[index]
