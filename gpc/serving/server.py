"""`gpc serve`: one controller (BC or a planner) answering ``act`` requests over a WebSocket.

The server is stateless about observations: each request carries the last ``n_obs_steps`` observations,
as ``gpc.harness.evaluation.run_group`` assembles them. It keeps one thing per episode: the episode's
random stream (``episode_generator(sampling_seed, episode)``, advanced decision by decision), so a
served episode draws exactly what `gpc eval` draws for the same seed, and scores the same.

One client controls at a time; the decision runs in a worker thread, so the event loop keeps answering
pings, refusals and disconnects while the planner works. Every request is checked (keys, shapes, dtypes,
finite values) before the controller sees it; a bad one gets one error message and the connection stays
open; a frame over ``max_size`` closes the connection (1009); nothing from the wire is ever executed.
"""

from __future__ import annotations

import asyncio
import hmac
import math
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from websockets.asyncio.server import ServerConnection, serve
from websockets.exceptions import ConnectionClosed

import gpc
from gpc.harness.evaluation import episode_generator
from gpc.models.planning.protocols import Controller
from gpc.serving import wire
from gpc.tasks import get_task
from gpc.tasks.base import GOAL_KEY

DEFAULT_PORT = 8765
LOOPBACK = "127.0.0.1"


@dataclass(frozen=True)
class ServeConfig:
    """Where and how the controller is served."""

    host: str = LOOPBACK  # loopback only unless opened on purpose
    port: int = DEFAULT_PORT  # 0: any free port (``ServedPolicy.port`` tells which)
    token: str | None = None  # a shared secret the client's hello must carry
    goal: str = "fixed"
    sampling_seed: int = 0  # with the episode seed, seeds each episode's random stream (as `gpc eval --sampling-seeds`)
    threads: int = 1  # torch threads of the planning thread (`gpc eval --threads`: the same numbers need the same count)
    max_size: int | None = None  # bytes per message at most (None: 4x a float64 request of the observations, at least 1 MiB)
    hello_timeout: float = 10.0  # seconds a new connection has to say hello


@dataclass(frozen=True)
class ObsSpec:
    """One observation key as a request must carry it: ``(n_obs_steps, *shape)`` of a dtype castable to ``dtype``."""

    shape: tuple[int, ...]
    dtype: np.dtype


class ServedPolicy:
    """The controller with what the wire needs: its observation spec, the handshake and checked decisions."""

    def __init__(self, controller: Controller, task: str, config: ServeConfig, label: str = "", summary: Mapping[str, Any] | None = None):
        self.controller, self.config, self.task = controller, config, get_task(task)
        self.task.check_goal(config.goal)
        self.n_obs_steps = int(controller.n_obs_steps)
        sample = self._first_observation()
        keys = tuple(controller.obs_keys) + ((GOAL_KEY,) if GOAL_KEY in sample and GOAL_KEY not in controller.obs_keys else ())
        self.spec = {k: ObsSpec(tuple(np.asarray(sample[k]).shape), np.asarray(sample[k]).dtype) for k in keys}
        warm = self.controller.plan({k: np.stack([np.asarray(sample[k])] * self.n_obs_steps)[None] for k in keys},
                                    [torch.Generator().manual_seed(0)])  # shapes of the answer, and the first call's set-up paid
        self.chunk_length, self.action_steps = int(warm.chunk.shape[1]), int(warm.actions.shape[1])
        box = self.task.layout.action
        self.metadata: dict[str, Any] = {
            "type": "metadata", "gpc_version": gpc.__version__, "wire_version": wire.WIRE_VERSION, "task": self.task.name,
            "goal": config.goal, "controller": label, "summary": dict(summary or {}),
            "observations": {k: {"shape": list(s.shape), "dtype": s.dtype.str} for k, s in self.spec.items()},
            "n_obs_steps": self.n_obs_steps, "action": {"dim": box.dim, "low": box.low, "high": box.high},
            "chunk_length": self.chunk_length, "action_steps": self.action_steps, "fps": self.task.fps,
            "sampling_seed": config.sampling_seed,
        }
        request = sum(8 * self.n_obs_steps * math.prod(s.shape) for s in self.spec.values())
        self.max_size = config.max_size or max(2**20, 4 * request)
        self._stream: tuple[int, int, torch.Generator] | None = None  # (episode, next decision, its generator)

    def _first_observation(self) -> dict[str, np.ndarray]:
        env = self.task.make_env(self.config.goal)
        env.reset(seed=0)
        keys = tuple(self.controller.obs_keys)
        return self.task.with_derived(self.task.observe(env, "img" in keys, self.task.sim_key in keys), keys)

    def check(self, request: Mapping[str, Any]) -> tuple[dict[str, np.ndarray], int, int]:
        """The request's observations cast to the spec, its episode and its decision index; ValueError names what is wrong."""
        episode, decision, obs = request.get("episode", 0), request.get("decision"), request.get("obs")
        for name, value in (("episode", episode), ("decision", decision)):
            if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                raise ValueError(f"{name} {value!r}: a non-negative integer is expected")
        assert isinstance(episode, int) and isinstance(decision, int)  # checked just above
        if not isinstance(obs, dict):
            raise ValueError("obs: a map of observation key to array is expected")
        missing, unknown = [k for k in self.spec if k not in obs], [k for k in obs if k not in self.spec]
        if missing or unknown:
            raise ValueError(f"obs: keys {sorted(obs)}; the controller reads {list(self.spec)}"
                             + (f" (missing {missing})" if missing else "") + (f" (unknown {unknown})" if unknown else ""))
        out = {}
        for key, spec in self.spec.items():
            value = obs[key]
            want = (self.n_obs_steps, *spec.shape)
            if not isinstance(value, np.ndarray):
                raise ValueError(f"obs.{key}: {type(value).__name__}; an array of shape {want} is expected")
            if value.shape != want:
                raise ValueError(f"obs.{key}: shape {value.shape}; expected {want} (the last {self.n_obs_steps} steps, oldest first)")
            if value.dtype.kind == "b" or not np.can_cast(value.dtype, spec.dtype, "same_kind"):
                raise ValueError(f"obs.{key}: dtype {value.dtype}; expected {spec.dtype} (or one that casts to it losslessly in kind)")
            if value.dtype.kind == "f" and not np.isfinite(value).all():
                raise ValueError(f"obs.{key}: holds NaN or infinite values")
            out[key] = value.astype(spec.dtype)
        return out, int(episode), int(decision)

    def generator(self, episode: int, decision: int) -> torch.Generator:
        """The episode's random stream at ``decision``: decision 0 starts it anew, later ones continue it in order."""
        if decision == 0:
            if hasattr(self.controller, "start"):
                self.controller.start([episode])  # as run_group names its episodes
            self._stream = (episode, 0, episode_generator(self.config.sampling_seed, episode))
        at = self._stream
        if at is None or at[0] != episode or at[1] != decision:
            now = "no episode started" if at is None else f"episode {at[0]} is at decision {at[1]}"
            raise ValueError(f"decision {decision} of episode {episode}: {now} (decisions of an episode go 0, 1, 2, ... "
                             "so its random stream is the one `gpc eval` draws)")
        return at[2]

    def decide(self, obs: dict[str, np.ndarray], episode: int, decision: int) -> dict[str, Any]:
        """One decision (in the planning thread): the chunk from now on, how many of its actions to execute, the seconds."""
        torch.set_num_threads(self.config.threads)
        gen = self.generator(episode, decision)
        t0 = time.perf_counter()
        with torch.no_grad():  # not inference_mode: gradient planners re-enable autograd inside
            plan = self.controller.plan({k: v[None] for k, v in obs.items()}, [gen])
        seconds = time.perf_counter() - t0
        assert self._stream is not None  # generator() set it
        self._stream = (episode, decision + 1, gen)
        return {"type": "action", "episode": episode, "decision": decision, "chunk": np.asarray(plan.chunk[0]),
                "action_steps": int(plan.actions.shape[1]), "planning_s": seconds,
                "parts_s": {k: float(v) for k, v in plan.seconds.items()}}


class PolicyServer:
    """The WebSocket front of a ``ServedPolicy``: handshake, token, one controlling client, checked requests."""

    def __init__(self, served: ServedPolicy) -> None:
        self.served, self.config = served, served.config
        self.pool = ThreadPoolExecutor(1, thread_name_prefix="gpc-plan")  # one controller: decisions in turn
        self.controller_conn: ServerConnection | None = None
        self.port: int | None = None

    async def handler(self, conn: ServerConnection) -> None:
        try:
            if not await self._hello(conn):
                return
            try:
                await self._serve(conn)
            finally:
                if self.controller_conn is conn:
                    self.controller_conn = None
        except ConnectionClosed:
            if self.controller_conn is conn:
                self.controller_conn = None

    async def _hello(self, conn: ServerConnection) -> bool:
        """The first message: the client's hello (with the token); the answer is the metadata, or one error and a close."""
        try:
            hello = wire.unpack(await asyncio.wait_for(conn.recv(), self.config.hello_timeout))
        except (TimeoutError, asyncio.TimeoutError):
            await self._refuse(conn, f"no hello within {self.config.hello_timeout:g} s", 1008)
            return False
        except wire.WireError as exc:
            await self._refuse(conn, f"hello: {exc}", 1003)
            return False
        if hello.get("type") != "hello":
            await self._refuse(conn, f"first message of type {hello.get('type')!r}: send a hello first", 1008)
            return False
        if self.config.token is not None:
            given = hello.get("token")
            if not isinstance(given, str) or not hmac.compare_digest(given.encode(), self.config.token.encode()):
                await self._refuse(conn, "token: missing or wrong (the server was started with --token / GPC_TOKEN)", 1008)
                return False
        if self.controller_conn is not None:
            await self._refuse(conn, "busy: another client controls this server; one client at a time", 1013)
            return False
        self.controller_conn = conn
        await conn.send(wire.pack(self.served.metadata))
        return True

    async def _refuse(self, conn: ServerConnection, text: str, code: int) -> None:
        await conn.send(wire.error(text))
        await conn.close(code, text[:120])

    async def _serve(self, conn: ServerConnection) -> None:
        loop = asyncio.get_running_loop()
        async for raw in conn:
            try:
                request = wire.unpack(raw)
                if request.get("type") != "act":
                    raise ValueError(f"request of type {request.get('type')!r}: the server answers act")
                obs, episode, decision = self.served.check(request)
            except ValueError as exc:  # WireError included: answered, and the connection stays open
                await conn.send(wire.error(str(exc), id=_id(raw)))
                continue
            job = loop.run_in_executor(self.pool, self._decide, obs, episode, decision)
            closed: asyncio.Future[Any] = asyncio.ensure_future(conn.wait_closed())
            await asyncio.wait([job, closed], return_when=asyncio.FIRST_COMPLETED)
            if not job.done():  # the client left mid-decision: free the seat now; the decision ends unread
                closed.cancel()
                job.add_done_callback(_drop)
                return
            closed.cancel()
            reply = job.result()
            if isinstance(reply, str):
                await conn.send(wire.error(reply))
                continue
            reply["id"] = request.get("id")
            await conn.send(wire.pack(reply))

    def _decide(self, obs: dict[str, np.ndarray], episode: int, decision: int) -> dict[str, Any] | str:
        try:
            return self.served.decide(obs, episode, decision)
        except ValueError as exc:  # the random stream's order; a controller's refusal of the input
            return str(exc)

    async def run(self, ready: Callable[[int], None] | None = None, stop: Callable[[], bool] | None = None,
                  stopped: asyncio.Event | None = None) -> None:
        """Serve until ``stop()`` says so (polled 4 times a second) or ``stopped`` is set."""
        stopped = stopped or asyncio.Event()
        async with serve(self.handler, self.config.host, self.config.port, max_size=self.served.max_size,
                         max_queue=4, compression=None) as server:
            self.port = next(iter(server.sockets)).getsockname()[1]
            if ready:
                ready(self.port)
            while not stopped.is_set() and not (stop and stop()):
                try:
                    await asyncio.wait_for(stopped.wait(), 0.25)
                except (TimeoutError, asyncio.TimeoutError):
                    pass
        self.pool.shutdown(wait=False, cancel_futures=True)


def _id(raw: Any) -> Any:
    """The request id of a message that failed its checks, when it can be read at all."""
    try:
        return wire.unpack(raw).get("id")
    except ValueError:
        return None


def _drop(job: asyncio.Future) -> None:
    job.exception()  # read, so an abandoned decision's error is not reported as never retrieved


class ServerThread:
    """A server on its own event loop in a daemon thread (tests, examples, notebooks); ``close()`` stops it."""

    def __init__(self, served: ServedPolicy) -> None:
        self.server = PolicyServer(served)
        self._started = threading.Event()
        self._loop = asyncio.new_event_loop()
        self._stopped: asyncio.Event | None = None
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._main, daemon=True, name="gpc-serve")
        self._thread.start()
        self._started.wait(60)
        if self._error is not None:
            raise self._error
        assert self.server.port is not None

    @property
    def port(self) -> int:
        assert self.server.port is not None
        return self.server.port

    def _main(self) -> None:
        async def main() -> None:
            self._stopped = asyncio.Event()
            await self.server.run(ready=lambda _: self._started.set(), stopped=self._stopped)

        try:
            self._loop.run_until_complete(main())
        except BaseException as exc:  # a port in use: reported by the constructor
            self._error = exc
            self._started.set()

    def close(self) -> None:
        if self._stopped is not None:
            self._loop.call_soon_threadsafe(self._stopped.set)
        self._thread.join(10)


def serve_recipe(recipe: Any, config: ServeConfig, announce: Callable[[str], None] = print) -> None:
    """Build the recipe's controller and serve it until SIGINT / SIGTERM (`gpc serve`)."""
    from gpc.harness import interrupts

    torch.set_num_threads(config.threads)
    served = ServedPolicy(recipe(), recipe.task, config, recipe.label, recipe.summary())

    def ready(port: int) -> None:
        local = config.host in (LOOPBACK, "localhost", "::1")
        guard = "token required" if config.token else "no token" if local else "OPEN TO THE NETWORK WITHOUT A TOKEN"
        announce(f"serving {recipe.label} ({served.task.name}) on ws://{config.host}:{port} ({guard}); "
                 f"{served.chunk_length} actions per chunk, {served.action_steps} executed per decision; Ctrl-C stops")

    asyncio.run(PolicyServer(served).run(ready=ready, stop=lambda: interrupts.requested() is not None))
    signum = interrupts.requested()
    if signum is not None:
        raise interrupts.Interrupted(signum, "the server stopped; it keeps nothing on disk")
