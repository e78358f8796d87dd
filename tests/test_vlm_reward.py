"""The zero-shot VLM reward against a real chat-completions server on the loopback interface.

The server (benchmarks/vlm_server.py) records what the openai client really sends and answers
from a script: a valid pick, a malformed or out-of-range answer, a slow reply, an HTTP error;
a closed port stands for an unreachable endpoint.
"""

from __future__ import annotations

import json
import logging
import socket

import cv2
import numpy as np
import pytest
import torch

from benchmarks.vlm_server import Reply, ScriptedChatServer
from gpc.models.rewards.vlm import GAP, VLMConfig, VLMReward, parse_choice, tile_frames
from gpc.tasks.pusht import LAYOUT

KEY_ENV, KEY = "GPC_TEST_VLM_KEY", "sk-test-secret-0123456789"
SIZE = 96


def dot(state: np.ndarray, goal: np.ndarray | None) -> np.ndarray:
    """A tiny renderer: a red disc at the state's (x, y) on white."""
    frame = np.full((SIZE, SIZE, 3), 255, np.uint8)
    cv2.circle(frame, (int(state[0]), int(state[1])), 9, (255, 0, 0), -1)
    return frame


def first_state(futures: torch.Tensor, goal=None) -> torch.Tensor:
    """A fallback reward with distinct scores: minus the final x."""
    return -futures[:, -1, 0]


def futures(k: int, seed: int = 0) -> torch.Tensor:
    """``(k, 4, 2)`` state futures whose final (x, y) lie inside a 96 px frame."""
    return torch.rand(k, 4, 2, generator=torch.Generator().manual_seed(seed)) * 70 + 13


def reward(server: ScriptedChatServer | str, fallback=first_state, **overrides) -> VLMReward:
    base_url = server if isinstance(server, str) else server.base_url
    config = VLMConfig(**{"base_url": base_url, "model": "test-vl", "timeout_s": 2.0, "max_retries": 0,
                          "backoff_s": 0.0, "api_key_env": KEY_ENV, **overrides})
    return VLMReward(config, dot, fallback, task_description="put the red disc in the corner")


@pytest.fixture(autouse=True)
def _env(monkeypatch):
    monkeypatch.setenv(KEY_ENV, KEY)
    monkeypatch.setenv("NO_PROXY", "127.0.0.1,localhost")


def warnings_of(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == "gpc.models.rewards.vlm" and r.levelno == logging.WARNING]


def test_a_valid_answer_selects_that_candidate_and_the_request_carries_image_prompt_and_settings(caplog):
    rendered = []

    def spy(state, goal):
        rendered.append(np.array(state))
        return dot(state, goal)

    f = futures(4)
    with ScriptedChatServer([Reply("3")]) as server:
        vlm = reward(server)
        vlm.render = spy
        scores = vlm(f, episode=0)
    assert scores.tolist() == [0.0, 0.0, 1.0, 0.0]
    assert vlm.selects is True
    (request,) = server.requests
    body = request.body
    assert body["model"] == "test-vl" and body["temperature"] == pytest.approx(0.2) and body["max_tokens"] == 16
    assert request.headers["authorization"] == f"Bearer {KEY}"
    text = request.text()
    assert "1 to 4" in text and "put the red disc in the corner" in text
    (image,) = request.images()  # one PNG data URL, 2 x 2 tiles of 96 px
    assert image.shape == (2 * SIZE + GAP, 2 * SIZE + GAP, 3)
    # the final states were rendered, in order, and tile i holds candidate i's frame (below its label)
    np.testing.assert_allclose(np.stack(rendered), f[:, -1].numpy())
    for i in range(4):
        r, c = divmod(i, 2)
        tile = image[r * (SIZE + GAP):r * (SIZE + GAP) + SIZE, c * (SIZE + GAP):c * (SIZE + GAP) + SIZE]
        np.testing.assert_array_equal(tile[24:], dot(f[i, -1].numpy(), None)[24:])
    stats = vlm.stats
    assert (stats["decisions"], stats["queries"], stats["fell_back"], stats["cache_hits"]) == (1, 1, 0, 0)
    assert stats["prompt_tokens"] > 49 and stats["completion_tokens"] == 1 and stats["seconds"] > 0
    assert not warnings_of(caplog)
    # the key is read from the environment and kept out of everything we show or store
    assert KEY not in json.dumps(stats) and KEY not in repr(vlm) and KEY not in repr(vlm.config)


def test_frame_futures_are_used_directly_without_rendering():
    frames = torch.rand(3, 2, 3, 48, 48)  # (K, T, 3, H, W) in [0, 1], smaller than a tile
    with ScriptedChatServer([Reply("2")]) as server:
        vlm = reward(server)
        vlm.render = None
        assert vlm(frames).tolist() == [0.0, 1.0, 0.0]
        hwc = (frames[:, :, :, :SIZE // 2] * 255).to(torch.uint8).permute(0, 1, 3, 4, 2)  # (K, T, H, W, 3)
        assert vlm(hwc).tolist() == [0.0, 1.0, 0.0]
    first, second = (r.images()[0] for r in server.requests)
    assert first.shape == second.shape == (2 * SIZE + GAP, 2 * SIZE + GAP, 3)  # 3 tiles: a 2 x 2 grid
    expected = cv2.resize(np.round(frames[1, -1].permute(1, 2, 0).numpy() * 255).astype(np.uint8), (SIZE, SIZE),
                          interpolation=cv2.INTER_AREA)
    np.testing.assert_array_equal(first[24:SIZE, SIZE + GAP:], expected[24:])
    assert (first[SIZE + GAP:, SIZE + GAP:] == 128).all()  # the unused cell stays grey


@pytest.mark.parametrize("answer, reason", [("I like the second", "malformed"), ("99", "out_of_range"),
                                            ("0", "out_of_range"), ("", "malformed")])
def test_an_unusable_answer_falls_back_to_the_fallback_rewards_scores(answer, reason, caplog):
    f = futures(5)
    with ScriptedChatServer([Reply(answer)]) as server:
        vlm = reward(server)
        scores = vlm(f, episode=7)
    torch.testing.assert_close(scores, first_state(f))
    stats = vlm.stats
    assert stats["fell_back"] == 1 and stats["fallbacks"][reason] == 1 and stats["queries"] == 1
    assert sum(stats["fallbacks"].values()) == 1
    (warning,) = warnings_of(caplog)
    assert reason in warning and "episode 7" in warning and "\n" not in warning


def test_a_slow_server_times_out_retries_once_then_falls_back_to_the_first_proposal(caplog):
    with ScriptedChatServer([Reply("2", delay_s=1.5)]) as server:
        vlm = reward(server, fallback=None, timeout_s=0.2, max_retries=1, backoff_s=0.01)
        scores = vlm(futures(3), episode=0)
        assert len(server.requests) == 2
    assert scores.tolist() == [1.0, 0.0, 0.0]
    stats = vlm.stats
    assert (stats["queries"], stats["retries"], stats["fallbacks"]["timeout"]) == (2, 1, 1)
    assert 0.4 <= stats["seconds"] < 1.2  # two attempts of ~0.2 s, not the server's 1.5 s
    assert "timeout" in warnings_of(caplog)[0]


def test_server_errors_are_retried_with_exponential_backoff_and_client_errors_are_not():
    f = futures(4)
    with ScriptedChatServer([Reply(status=500)]) as server:
        vlm = reward(server, max_retries=2, backoff_s=0.05)
        torch.testing.assert_close(vlm(f), first_state(f))
    assert len(server.requests) == 3 and vlm.stats["queries"] == 3 and vlm.stats["fallbacks"]["http_error"] == 1
    gaps = np.diff([r.arrived for r in server.requests])
    assert gaps[0] >= 0.05 and gaps[1] >= 0.10 and gaps[1] > gaps[0]
    with ScriptedChatServer([Reply(status=500), Reply("4")]) as server:  # recovers on the retry
        vlm = reward(server, max_retries=2, backoff_s=0.01)
        assert vlm(f).tolist() == [0.0, 0.0, 0.0, 1.0]
    assert vlm.stats["queries"] == 2 and vlm.stats["fell_back"] == 0
    with ScriptedChatServer([Reply(status=400)]) as server:
        vlm = reward(server, max_retries=3, backoff_s=0.01)
        vlm(f)
    assert len(server.requests) == 1 and vlm.stats["fallbacks"]["http_error"] == 1


def test_an_unreachable_endpoint_falls_back_and_the_eval_goes_on(caplog):
    with socket.socket() as s:  # a port nothing listens on once closed
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    vlm = reward(f"http://127.0.0.1:{port}/v1", fallback=None, max_retries=1, backoff_s=0.01)
    for episode in (0, 0, 0, 1, 1):  # one warning per episode, every fallback counted
        assert vlm(futures(3, seed=episode), episode=episode).tolist() == [1.0, 0.0, 0.0]
    stats = vlm.stats
    assert stats["fell_back"] == 5 and stats["fallbacks"]["unreachable"] == 5
    assert stats["queries"] == 5 and stats["retries"] == 0  # a refused connection is not retried (timeouts, 5xx, 429 are)
    messages = warnings_of(caplog)
    assert len(messages) == 2 and "episode 0" in messages[0] and "episode 1" in messages[1]
    assert all("unreachable" in m and KEY not in m for m in messages)


def test_identical_requests_are_answered_from_the_cache_in_memory_and_on_disk(tmp_path):
    f = futures(6)
    with ScriptedChatServer([Reply("5")]) as server:
        vlm = reward(server, cache_dir=str(tmp_path / "cache"))
        assert vlm(f).argmax().item() == 4 and vlm(f).argmax().item() == 4
        assert len(server.requests) == 1 and vlm.stats["cache_hits"] == 1
        rerun = reward(server, cache_dir=str(tmp_path / "cache"))  # a re-run: a new process, same folder
        assert rerun(f).argmax().item() == 4
        assert len(server.requests) == 1 and rerun.stats["cache_hits"] == 1 and rerun.stats["queries"] == 0
        reward(server, cache_dir=str(tmp_path / "cache"), temperature=0.0)(f)  # another request: asked again
        vlm(futures(6, seed=1))  # other futures: asked again
        assert len(server.requests) == 3
    (entry, *_) = sorted((tmp_path / "cache").glob("*.json"))
    assert len(entry.stem) == 64 and KEY not in entry.read_text()


@pytest.mark.parametrize("field, value, option", [
    ("temperature", -1.0, "--vlm-temperature -1.0: must be in [0, 2]"), ("base_url", "localhost:8000", "--vlm-base-url"),
    ("model", " ", "--vlm-model"), ("timeout_s", 0.0, "--vlm-timeout"), ("max_retries", -1, "--vlm-retries"),
    ("prompt", "pick one", "--vlm-prompt"), ("prompt", "{k} {x}", "--vlm-prompt"), ("frame_size", 8, "--vlm-frame-size"),
    ("api_key_env", "sk-abc", "--vlm-key-env"),
])
def test_config_rejects_bad_values_naming_the_option(field, value, option):
    with pytest.raises(ValueError, match="^" + option.replace("[", r"\[").replace("]", r"\]").replace(".", r"\.")):
        VLMConfig(**{field: value})


def test_parse_choice_takes_the_first_integer_in_range():
    assert parse_choice("3", 4) == (2, None) and parse_choice(" Outcome 4.", 4) == (3, None)
    assert parse_choice("none", 4) == (None, "malformed") and parse_choice(None, 4) == (None, "malformed")
    assert parse_choice("5", 4) == (None, "out_of_range")


def test_tiles_are_numbered_and_laid_out_in_rows():
    frames = np.full((5, SIZE, SIZE, 3), 255, np.uint8)
    grid = tile_frames(frames, columns=5)
    assert grid.shape == (SIZE, 5 * SIZE + 4 * GAP, 3)
    label = grid[:20, :20]
    assert (label.min(axis=-1) < 64).any()  # a dark digit in the corner
    assert (grid[40:, :SIZE] == 255).all()


def test_pusht_frames_from_the_real_renderer_and_the_registration_fallback():
    from gpc.models.rewards.registration import RegistrationReward
    from gpc.tasks.pusht import render_state
    from gpc.tasks.pusht.geometry import GOAL_POSE, TEE_BOXES

    states = torch.tensor([[[100, 100, 256, 256, np.pi / 4]], [[400, 120, 300, 200, 1.0]],
                           [[200, 420, 150, 330, 2.5]]], dtype=torch.float64).repeat(1, 3, 1)  # (K=3, T=3, 5)
    goal = torch.tensor(GOAL_POSE, dtype=torch.float64)
    registration = RegistrationReward(torch.tensor(TEE_BOXES).reshape(-1, 2), goal, LAYOUT.pose_dims)
    with ScriptedChatServer([Reply("2"), Reply("no idea")]) as server:
        vlm = VLMReward(VLMConfig(base_url=server.base_url, model="test-vl", timeout_s=2.0, max_retries=0,
                                  api_key_env=KEY_ENV),
                        render=lambda s, g: render_state(s, g, SIZE), fallback=registration,
                        task_description="push the grey T onto the green T")
        assert vlm(states, goal).tolist() == [0.0, 1.0, 0.0]
        flipped = states.flip(0)  # another image, so not the cached answer
        torch.testing.assert_close(vlm(flipped, goal), registration(flipped, goal))
    image = server.requests[0].images()[0]
    tile = image[:SIZE, SIZE + GAP:2 * SIZE + GAP]
    np.testing.assert_array_equal(tile[24:], render_state(states[1, -1].numpy(), GOAL_POSE, SIZE)[24:])
    assert vlm.stats["fallbacks"]["malformed"] == 1


@pytest.mark.parametrize("raw", [b"<html>502 from a proxy</html>", b'{"choices": "no"}', b"", b'{"choices": [{"message": {}}]}',
                                 b'{"choices": [{"message": {"content": "' + b"9" * 200_000 + b'"}}]}'])
def test_a_broken_answer_of_any_shape_falls_back_and_the_eval_goes_on(raw):
    """HTTP 200 with a body that is not JSON, JSON of another schema, nothing, or a huge answer: counted, never raised."""
    with ScriptedChatServer([Reply(raw=raw)]) as server:
        vlm = reward(server, fallback=None)
        assert vlm(futures(3)).tolist() == [1.0, 0.0, 0.0]  # the first proposal
    stats = vlm.stats
    assert stats["fell_back"] == 1 and stats["queries"] == 1 and stats["retries"] == 0
    assert stats["fallbacks"]["malformed"] + stats["fallbacks"]["out_of_range"] == 1
