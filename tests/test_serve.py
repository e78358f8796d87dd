"""`gpc serve` and `gpc.client`: a real server (a `gpc serve` process, or the same server in a thread) and a real
client on 127.0.0.1 with an ephemeral port; the tiny trained checkpoints of the fault tests.

Served synchronous episodes score exactly what `gpc eval` scores on the same seeds; bad input gets one error and the
server goes on serving; nothing from the wire is unpickled; the server listens on the loopback address by default.
"""

from __future__ import annotations

import json
import os
import pickle
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
from faults import ENV, GPC, inline, one_line, wait_for

from gpc.client import AsyncChunks, Decision, History, PolicyClient, ServerError
from gpc.harness.recipes import make_recipe
from gpc.serving import wire
from gpc.serving.robot import SimRobot, sync_episode
from gpc.serving.server import ServeConfig, ServedPolicy, ServerThread

pytestmark = pytest.mark.usefixtures("one_thread")
SEEDS = (100000, 100001)
STEPS = 40


def serve_thread(recipe, controller=None, **config) -> ServerThread:
    served = ServedPolicy(controller or recipe(), recipe.task, ServeConfig(port=0, **config), recipe.label, recipe.summary())
    return ServerThread(served)


@pytest.fixture(scope="module")
def bc(tiny_pusht):
    return make_recipe(tiny_pusht["policy"], "bc")


@pytest.fixture(scope="module")
def server(bc):
    srv = serve_thread(bc)
    yield srv
    srv.close()


def url(srv) -> str:
    return f"ws://127.0.0.1:{srv.port}"


def act_request(client: PolicyClient, decision: int = 0, **obs_changes) -> dict:
    """A valid act request for seed 100000's first step, with ``obs_changes`` replacing (or, None, removing) keys."""
    robot = SimRobot(client)
    obs = client.history(robot.reset(SEEDS[0])).arrays()
    for key, value in obs_changes.items():
        obs.pop(key) if value is None else obs.__setitem__(key, value)
    return {"type": "act", "id": 7, "episode": SEEDS[0], "decision": decision, "obs": obs}


def with_state(request: dict, dtype: str, nbytes: int) -> bytes:
    """``request`` with its state spelled by hand (what ``wire.pack`` itself never sends): ``dtype``, ``nbytes`` of zeros."""
    state = {"__nd__": 1, "dtype": dtype, "shape": [2, 5], "data": b"\0" * nbytes}
    return msgpack.packb({**request, "obs": {**request["obs"], "state": state}}, default=wire._encode)


def answer(client: PolicyClient, raw: bytes) -> dict:
    client.ws.send(raw)
    return wire.unpack(client.ws.recv(30))


# ---------------------------------------------------------------------- the handshake and the equality with gpc eval
def test_handshake_tells_the_task_observations_action_box_and_chunk(server, bc):
    with PolicyClient(url(server)) as client:
        meta = client.metadata
    assert meta["type"] == "metadata" and meta["wire_version"] == wire.WIRE_VERSION and meta["gpc_version"]
    assert meta["task"] == "pusht" and meta["controller"] == "bc" and meta["goal"] == "fixed"
    assert meta["observations"] == {"keypoint": {"shape": [9, 2], "dtype": "<f4"}, "state": {"shape": [5], "dtype": "<f4"}}
    assert meta["n_obs_steps"] == 2 and meta["action"] == {"dim": 2, "low": 0.0, "high": 512.0}
    assert (meta["chunk_length"], meta["action_steps"], meta["fps"]) == (15, 8, 10)


@pytest.mark.parametrize("planner", ["bc", "rank"])
def test_served_episodes_score_what_gpc_eval_scores(tiny_pusht, tmp_path, planner):
    extra = ["--planner", "rank", "-K", "3", "--world-model", str(tiny_pusht["wm"])] if planner == "rank" else []
    code, out = inline("eval", str(tiny_pusht["policy"]), *extra, "--seeds", ",".join(map(str, SEEDS)),
                       "--max-steps", str(STEPS), "--batch", "1", "--out", str(tmp_path / "eval"))
    assert code == 0, out
    evaluated = {r["seed"]: r for r in json.loads((tmp_path / "eval" / "episodes.json").read_text())}
    recipe = make_recipe(tiny_pusht["policy"], planner, **({"world_model": str(tiny_pusht["wm"]), "k": 3} if extra else {}))
    srv = serve_thread(recipe)
    try:
        with PolicyClient(url(srv)) as client:
            served = [sync_episode(client, seed, STEPS) for seed in SEEDS]
    finally:
        srv.close()
    for row in served:
        want = evaluated[row["seed"]]
        assert (row["score"], row["success"], row["steps"]) == (want["score"], want["success"], want["steps"])
        # The same trajectory, not only the same best reward (a served decision is a batch of one, as --batch 1's).
        assert row["final_state"] == want["final_state"]
    assert len({tuple(r["final_state"]) for r in served}) == 2


# ---------------------------------------------------------------------- who may connect
def test_gpc_serve_listens_on_loopback_only_and_wants_the_token(tiny_pusht):
    proc = subprocess.Popen([*GPC, "serve", str(tiny_pusht["policy"]), "--port", "0"], env={**ENV, "GPC_TOKEN": "s3cret"},
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()  # the announcement comes once the socket listens
        found = re.search(r"ws://([\d.]+):(\d+)", line)
        assert found and found.group(1) == "127.0.0.1", line
        port = int(found.group(2))
        assert listening_addresses(port) == {"127.0.0.1"}
        with pytest.raises(ServerError, match="token"):
            PolicyClient(f"ws://127.0.0.1:{port}", token="wrong")
        with pytest.raises(ServerError, match="token"):
            PolicyClient(f"ws://127.0.0.1:{port}")
        with PolicyClient(f"ws://127.0.0.1:{port}", token="s3cret") as client:
            robot = SimRobot(client)
            client.reset(SEEDS[0])
            decision = client.act(client.history(robot.reset(SEEDS[0])).arrays())
            assert decision.chunk.shape == (15, 2) and decision.action_steps == 8
    finally:
        code, err = finish_serving(proc)
    one_line((code, err), 130, "stopped by SIGINT")


def finish_serving(proc: subprocess.Popen) -> tuple[int, str]:
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    return proc.returncode, err


def listening_addresses(port: int) -> set[str]:
    """The local addresses listening on ``port`` (Linux's /proc/net/tcp and tcp6)."""
    found = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        if not Path(table).exists():
            continue
        for row in Path(table).read_text().splitlines()[1:]:
            local, state = row.split()[1], row.split()[3]
            address, hex_port = local.split(":")
            if state == "0A" and int(hex_port, 16) == port:
                found.add(socket.inet_ntop(socket.AF_INET, bytes.fromhex(address)[::-1]) if len(address) == 8 else address)
    if not found:
        pytest.skip("no /proc/net/tcp to read the listening address from")
    return found


def test_a_second_client_is_refused_while_the_first_keeps_control(server):
    with PolicyClient(url(server)) as first:
        with pytest.raises(ServerError, match="another client controls"):
            PolicyClient(url(server))
        reply = answer(first, wire.pack(act_request(first)))
        assert reply["type"] == "action" and reply["chunk"].shape == (15, 2)
    wait_for(lambda: PolicyClient(url(server)).close() is None, 10)  # the seat is free once the first leaves


# ---------------------------------------------------------------------- bad input: one error, then the next request served
def test_bad_requests_get_one_error_and_the_connection_goes_on(server, tmp_path):
    marker = tmp_path / "ran"

    class Payload:  # what a pickle on the wire would run
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    with PolicyClient(url(server)) as client:
        good = act_request(client)
        bad = {
            "malformed msgpack": (b"\xc1\x00", "malformed msgpack"),
            "a raw pickle": (pickle.dumps(Payload()), "malformed msgpack"),
            "a pickle in an extension type": (msgpack.packb({"type": "act", "obs": msgpack.ExtType(1, pickle.dumps(Payload()))}),
                                              "extension type"),
            "an object array": (with_state(good, "|O", 80), "dtype '|O'"),
            "an unknown key": (wire.pack(act_request(client, extra=np.zeros((2, 3), np.float32))), "unknown ['extra']"),
            "a missing key": (wire.pack(act_request(client, keypoint=None)), "missing ['keypoint']"),
            "a wrong shape": (wire.pack(act_request(client, state=np.zeros((1, 5), np.float32))), "obs.state: shape (1, 5)"),
            "a complex array": (with_state(good, "<c8", 80), "dtype '<c8'"),
            "an image dtype for floats": (wire.pack(act_request(client, state=np.zeros((2, 5), bool))), "obs.state: dtype bool"),
            "NaN": (wire.pack(act_request(client, state=np.full((2, 5), np.nan, np.float32))), "obs.state: holds NaN"),
            "an array shorter than its shape": (with_state(good, "<f4", 8), "data is not 10 items"),
            "a decision out of order": (wire.pack({**good, "decision": 3}), "decision 3 of episode 100000"),
            "another type": (wire.pack({"type": "shutdown"}), "request of type 'shutdown'"),
        }
        for case, (raw, fragment) in bad.items():
            reply = answer(client, raw)
            assert reply["type"] == "error" and fragment in reply["error"], (case, reply)
            assert "\n" not in reply["error"]
        assert not marker.exists()  # nothing from the wire ran
        reply = answer(client, wire.pack(good))
        assert reply["type"] == "action" and reply["id"] == 7 and np.isfinite(reply["chunk"]).all()


def test_an_oversize_message_closes_that_connection_and_the_server_serves_the_next(server):
    client = PolicyClient(url(server))
    client.ws.send(b"\0" * (server.server.served.max_size + 1))
    with pytest.raises(Exception) as closed:
        client.ws.recv(30)
    assert closed.value.rcvd.code == 1009  # websockets' "message too big"
    with PolicyClient(url(server)) as again:
        assert answer(again, wire.pack(act_request(again)))["type"] == "action"


class Slow:
    """The controller, with each decision taking ``delay`` seconds more (a GPU planner's seconds, on a tiny model)."""

    def __init__(self, controller, delay: float) -> None:
        self.inner, self.delay = controller, delay
        self.obs_keys, self.n_obs_steps = controller.obs_keys, controller.n_obs_steps

    def plan(self, obs, generators):
        time.sleep(self.delay)
        return self.inner.plan(obs, generators)


def test_a_client_gone_mid_decision_frees_the_seat_and_the_next_client_is_served(bc):
    srv = serve_thread(bc, Slow(bc(), 1.5))
    try:
        client = PolicyClient(url(srv))
        client.ws.send(wire.pack(act_request(client)))
        time.sleep(0.3)  # the decision is running
        client.close()
        t0 = time.perf_counter()
        with PolicyClient(url(srv)) as nxt:  # seated while the abandoned decision still runs
            assert time.perf_counter() - t0 < 1.0
            reply = answer(nxt, wire.pack(act_request(nxt)))
            assert reply["type"] == "action" and reply["planning_s"] >= 1.5
    finally:
        srv.close()


# ---------------------------------------------------------------------- the client
def test_the_client_imports_without_torch():
    code = "import sys, gpc.client; assert 'torch' not in sys.modules, sorted(m for m in sys.modules if 'torch' in m)"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr


class FakeClient:
    """A server that takes ``delay`` seconds and answers, for the step it is asked at, the chunk [at, at+1, ...]
    (12 actions, 4 executed per decision)."""

    metadata = {"fps": 100, "observations": {"step": {}}, "n_obs_steps": 1}

    def __init__(self, delay: float) -> None:
        self.delay = delay

    def reset(self, episode: int) -> None:
        pass

    def history(self, first) -> History:
        return History(["step"], 1, first)

    def act(self, obs_history) -> Decision:
        time.sleep(self.delay)
        at = float(obs_history["step"][-1])
        chunk = (at + np.arange(12, dtype=np.float32))[:, None]
        return Decision(chunk, 4, self.delay, self.delay, 0, 0, 0, 0)


@pytest.mark.parametrize("delay", [0.0, 0.03, 0.2])
def test_async_chunks_execute_the_action_planned_for_each_step(delay):
    runner = AsyncChunks(FakeClient(delay), fps=100)  # type: ignore[arg-type]
    runner.start({"step": np.float32(0)})
    for step in range(40):
        assert float(runner.next_action()[0]) == step  # the new chunk's passed actions are skipped, never replayed
        time.sleep(0.01)
        runner.observe({"step": np.float32(step + 1)})
    runner.wait_pending()
    assert len(runner.stats.skipped) >= 40 // 12  # decisions went on while the robot moved
    assert max(runner.stats.skipped) <= 12 - 4  # a chunk switched to keeps at least its action_steps actions
    # The robot waits only where going on would leave the coming chunk fewer than 4 actions (8 ticks of 10 ms or more).
    assert (max(runner.stats.idle_s) > 0) == (delay == 0.2), runner.stats.idle_s
