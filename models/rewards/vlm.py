"""A zero-shot reward that selects rather than scores: a vision-language model picks the best future.

The K predicted final frames are tiled into one image, numbered 1..K, and sent with a task
prompt to any OpenAI-compatible chat-completions endpoint (vLLM, Ollama, llama.cpp's
server, a hosted API); the candidate it names gets 1.0, the others 0.0. One query per
decision. Nothing here may stop an evaluation: a timeout, an HTTP error, an unreachable
endpoint or an answer that names no candidate falls back to another reward (or to the
first proposal), logs one line per episode and is counted in ``stats``. Answers are cached
by a hash of the request, so a re-run sends no second query. The API key is read from an
environment variable when the client is built and is kept nowhere else.
"""

from __future__ import annotations

import base64
import hashlib
import json
import logging
import math
import os
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from gpc.models.world_models.pictures import last_step_pictures

log = logging.getLogger(__name__)

DEFAULT_PROMPT = (
    "The image shows {k} possible outcomes of a robot's next move, numbered 1 to {k} in their "
    "top-left corners. Task: {task}. Which numbered outcome is closest to completing the task? "
    "Answer with the number only."
)
GAP = 2  # px of grey between tiles, so the model sees where one outcome ends
REASONS = ("timeout", "http_error", "unreachable", "malformed", "out_of_range")
MAX_ANSWER = 1000  # characters of an answer kept (parsed and cached); the answer is a number
_NUMBER = re.compile(r"\d+")

Render = Callable[[np.ndarray, "np.ndarray | None"], np.ndarray]
FallbackReward = Callable[..., torch.Tensor]


@dataclass(frozen=True)
class VLMConfig:
    """Where and how to ask; the CLI option each field answers to is in its error messages."""

    base_url: str = "http://localhost:8000/v1"  # OpenAI-compatible root (vLLM's default port)
    model: str = "Qwen/Qwen2.5-VL-7B-Instruct"
    temperature: float = 0.2  # low: the same futures should get the same pick
    timeout_s: float = 30.0  # per request
    max_retries: int = 2  # extra attempts after a timeout, a 5xx or a 429 (a refused or failed connection is not retried)
    backoff_s: float = 1.0  # wait before retry i (i = 1, 2, ...) is backoff_s * 2**(i - 1)
    api_key_env: str = "OPENAI_API_KEY"  # the variable holding the key; unset -> a dummy (local servers ignore it)
    prompt: str = DEFAULT_PROMPT  # {k}: number of candidates, {task}: the task description
    frame_size: int = 96  # px per tile side
    columns: int = 0  # tiles per row; 0: ceil(sqrt(K))
    max_tokens: int = 16  # the answer is a number
    cache_dir: str | None = None  # one JSON file per answered request; None: in memory only

    def __post_init__(self) -> None:
        if not re.match(r"^https?://[^/\s]+", self.base_url):
            raise ValueError(f"--vlm-base-url {self.base_url!r}: need http(s)://host[:port][/path]")
        if not self.model.strip():
            raise ValueError("--vlm-model '': name the served model")
        if not 0.0 <= self.temperature <= 2.0:
            raise ValueError(f"--vlm-temperature {self.temperature}: must be in [0, 2]")
        if not self.timeout_s > 0:
            raise ValueError(f"--vlm-timeout {self.timeout_s}: must be > 0 seconds")
        if self.max_retries < 0:
            raise ValueError(f"--vlm-retries {self.max_retries}: must be >= 0")
        if self.backoff_s < 0:
            raise ValueError(f"--vlm-backoff {self.backoff_s}: must be >= 0 seconds")
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", self.api_key_env):
            raise ValueError(f"--vlm-key-env {self.api_key_env!r}: must be an environment variable name")
        if "{k}" not in self.prompt:
            raise ValueError("--vlm-prompt: must contain {k} (the number of candidates)")
        try:
            self.prompt.format(k=2, task="t")
        except (KeyError, IndexError, ValueError) as err:
            raise ValueError(f"--vlm-prompt: only {{k}} and {{task}} may be placeholders ({err!r})") from None
        if not 16 <= self.frame_size <= 1024:
            raise ValueError(f"--vlm-frame-size {self.frame_size}: must be in [16, 1024] px")
        if self.columns < 0:
            raise ValueError(f"--vlm-columns {self.columns}: must be >= 0 (0: square grid)")
        if self.max_tokens < 1:
            raise ValueError(f"--vlm-max-tokens {self.max_tokens}: must be >= 1")


def grid_shape(k: int, columns: int = 0) -> tuple[int, int]:
    """(rows, cols) of the tiling of k frames."""
    cols = min(k, columns) if columns else math.ceil(math.sqrt(k))
    return math.ceil(k / cols), cols


def tile_frames(frames: np.ndarray, columns: int = 0) -> np.ndarray:
    """``(K, S, S, 3)`` uint8 -> one ``(rows*S + (rows-1)*GAP, cols*S + (cols-1)*GAP, 3)`` image, numbered 1..K."""
    k, size = frames.shape[0], frames.shape[1]
    rows, cols = grid_shape(k, columns)
    grid = np.full((rows * size + (rows - 1) * GAP, cols * size + (cols - 1) * GAP, 3), 128, np.uint8)
    scale = size / 220.0  # ~13 px tall digits on a 96 px tile
    for i, frame in enumerate(frames):
        tile = frame.copy()
        org = (max(2, size // 32), max(10, int(size * 0.16)))
        label = str(i + 1)
        cv2.putText(tile, label, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 3, cv2.LINE_AA)
        cv2.putText(tile, label, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 1, cv2.LINE_AA)
        r, c = divmod(i, cols)
        y, x = r * (size + GAP), c * (size + GAP)
        grid[y:y + size, x:x + size] = tile
    return grid


def parse_choice(answer: str | None, k: int) -> tuple[int | None, str | None]:
    """The first integer in the answer, as a 0-based index -> (index, None), or (None, failure reason)."""
    match = _NUMBER.search(answer or "")
    if match is None:
        return None, "malformed"
    number = int(match.group())
    return (number - 1, None) if 1 <= number <= k else (None, "out_of_range")


class _QueryFailed(Exception):
    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason


class VLMReward:
    """Selects one of K predicted futures by asking a vision-language model; ``(K, T, ...)`` -> ``(K,)``.

    ``render(state (D,), goal) -> (S, S, 3) uint8`` draws a predicted final *state*; futures that
    are already frames, ``(K, T, 3, H, W)`` float in [0, 1] or ``(K, T, H, W, 3)`` uint8, are used
    as they are. ``fallback`` scores the futures when the model gives no usable answer (None: pick
    proposal 0). Scores only rank (1 for the pick, 0 otherwise) and carry no gradient.
    """

    selects = True  # planners: the scores rank, they are not a value to optimise

    def __init__(self, config: VLMConfig, render: Render | None = None, fallback: FallbackReward | None = None,
                 task_description: str = "make the scene match the goal shown in it") -> None:
        self.config = config
        self.render = render
        self.fallback = fallback
        self.task_description = task_description
        self._client: Any = None
        self._memory: dict[str, str] = {}
        self._warned: set[int | None] = set()
        self._stats: dict[str, Any] = {
            "decisions": 0, "queries": 0, "retries": 0, "cache_hits": 0, "fell_back": 0,
            "fallbacks": dict.fromkeys(REASONS, 0), "prompt_tokens": 0, "completion_tokens": 0, "seconds": 0.0,
        }

    def __repr__(self) -> str:
        return f"VLMReward(model={self.config.model!r}, base_url={self.config.base_url!r})"

    @property
    def stats(self) -> dict[str, Any]:
        """JSON-ready counts: queries sent (retries included), cache hits, fallbacks by reason, tokens, seconds."""
        return {**self._stats, "fallbacks": dict(self._stats["fallbacks"])}

    def __call__(self, futures: torch.Tensor, goal: Any = None, episode: int | None = None) -> torch.Tensor:
        """``(K, T, ...)`` futures -> ``(K,)`` float scores: 1 for the chosen candidate, 0 for the rest."""
        self._stats["decisions"] += 1
        k = futures.shape[0]
        frames = self.final_frames(futures, goal)
        image = tile_frames(frames, self.config.columns)
        prompt = self.config.prompt.format(k=k, task=self.task_description)
        try:
            answer = self._answer(prompt, image)
            index, reason = parse_choice(answer, k)
            if index is None:
                assert reason is not None  # parse_choice names a reason with every missing index
                raise _QueryFailed(reason, f"answer {answer[:60]!r} names no candidate in 1..{k}")
        except _QueryFailed as failure:
            return self._fall_back(futures, goal, episode, failure)
        return _one_hot(futures, index)

    def final_frames(self, futures: torch.Tensor, goal: Any = None) -> np.ndarray:
        """``(K, T, ...)`` -> ``(K, S, S, 3)`` uint8 frames of the last predicted step, S = frame_size."""
        frames = last_step_pictures(futures, self.render, goal)
        size = self.config.frame_size
        out = np.empty((len(frames), size, size, 3), np.uint8)
        for i, frame in enumerate(frames):
            if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
                raise ValueError(f"render: expected (S, S, 3) uint8, got {frame.shape} {frame.dtype}")
            out[i] = frame if frame.shape[:2] == (size, size) else cv2.resize(frame, (size, size), interpolation=cv2.INTER_AREA)
        return out

    # --- the query -----------------------------------------------------------------------------

    def _answer(self, prompt: str, image: np.ndarray) -> str:
        """The model's text for this prompt and image, from the cache when this exact request was answered."""
        ok, png = cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
        assert ok, "PNG encoding failed"
        png_bytes = png.tobytes()
        key = self._cache_key(prompt, png_bytes)
        cached = self._cache_get(key)
        if cached is not None:
            self._stats["cache_hits"] += 1
            return cached
        answer = self._query(prompt, base64.b64encode(png_bytes).decode("ascii"))
        self._cache_put(key, answer)
        return answer

    def _query(self, prompt: str, png_b64: str) -> str:
        """One request with our own retry loop (the client's is off, so every attempt is counted)."""
        import openai

        cfg = self.config
        messages = [{"role": "user", "content": [
            {"type": "text", "text": prompt},
            {"type": "image_url", "image_url": {"url": f"data:image/png;base64,{png_b64}"}},
        ]}]
        failure = _QueryFailed("unreachable", "no attempt made")
        for attempt in range(cfg.max_retries + 1):
            if attempt:
                self._stats["retries"] += 1
                time.sleep(cfg.backoff_s * 2 ** (attempt - 1))
            self._stats["queries"] += 1
            t0 = time.perf_counter()
            try:
                response = self._get_client().chat.completions.create(
                    model=cfg.model, messages=messages, temperature=cfg.temperature, max_tokens=cfg.max_tokens)
                return self._content(response)
            except openai.APITimeoutError:
                failure = _QueryFailed("timeout", f"no answer within {cfg.timeout_s} s")
            except openai.APIConnectionError as err:  # refused, unresolvable, reset: retrying the same second will not help
                failure = _QueryFailed("unreachable", f"cannot connect to {cfg.base_url} ({type(err.__cause__).__name__})")
                break
            except openai.APIStatusError as err:
                failure = _QueryFailed("http_error", f"HTTP {err.status_code} from {cfg.base_url}")
                if err.status_code < 500 and err.status_code != 429:
                    break  # a client error will not go away on retry
            except _QueryFailed as err:  # a readable response without an answer in it
                failure = err
                break
            except Exception as err:  # an unreadable body (not JSON, another schema): any failure of a reward falls back
                failure = _QueryFailed("malformed", f"unreadable response ({type(err).__name__})")
                break
            finally:
                self._stats["seconds"] += time.perf_counter() - t0
        raise failure

    def _content(self, response: Any) -> str:
        usage = getattr(response, "usage", None)
        if usage is not None:
            self._stats["prompt_tokens"] += int(getattr(usage, "prompt_tokens", 0) or 0)
            self._stats["completion_tokens"] += int(getattr(usage, "completion_tokens", 0) or 0)
        choices = getattr(response, "choices", None) or []
        content = getattr(getattr(choices[0], "message", None), "content", None) if choices else None
        if not isinstance(content, str):
            raise _QueryFailed("malformed", "response has no message content")
        return content[:MAX_ANSWER]

    def _get_client(self) -> Any:
        if self._client is None:
            import openai

            key = os.environ.get(self.config.api_key_env) or "not-needed"  # local servers ignore the key
            self._client = openai.OpenAI(base_url=self.config.base_url, api_key=key,
                                         timeout=self.config.timeout_s, max_retries=0)
        return self._client

    def _fall_back(self, futures: torch.Tensor, goal: Any, episode: int | None, failure: _QueryFailed) -> torch.Tensor:
        self._stats["fell_back"] += 1
        self._stats["fallbacks"][failure.reason] += 1
        if episode not in self._warned:
            self._warned.add(episode)
            to = "the fallback reward" if self.fallback is not None else "the first proposal"
            log.warning("VLM reward fell back to %s in episode %s (%s: %s); later fallbacks in this episode are only counted",
                        to, episode, failure.reason, failure)
        if self.fallback is None:
            return _one_hot(futures, 0)
        with torch.no_grad():
            return self.fallback(futures) if goal is None else self.fallback(futures, goal)

    # --- cache ---------------------------------------------------------------------------------

    def _cache_key(self, prompt: str, png: bytes) -> str:
        cfg = self.config
        head = json.dumps([cfg.model, prompt, cfg.temperature, cfg.max_tokens]).encode()
        return hashlib.sha256(head + b"\0" + png).hexdigest()

    def _cache_get(self, key: str) -> str | None:
        if key in self._memory:
            return self._memory[key]
        if self.config.cache_dir is not None:
            path = Path(self.config.cache_dir) / f"{key}.json"
            try:
                answer = json.loads(path.read_text())["answer"]
            except (OSError, ValueError, KeyError, TypeError):
                return None
            if not isinstance(answer, str):  # a damaged cache entry is asked again, not trusted
                return None
            self._memory[key] = answer
            return answer
        return None

    def _cache_put(self, key: str, answer: str) -> None:
        self._memory[key] = answer
        if self.config.cache_dir is not None:
            folder = Path(self.config.cache_dir)
            tmp = folder / f"{key}.json.tmp{os.getpid()}"
            try:
                folder.mkdir(parents=True, exist_ok=True)
                tmp.write_text(json.dumps({"model": self.config.model, "answer": answer}))
                os.replace(tmp, folder / f"{key}.json")  # atomic: parallel workers never read half a file
            except OSError:  # a full or read-only disk costs the cache, never the eval
                tmp.unlink(missing_ok=True)
                self._stats["cache_write_failures"] = self._stats.get("cache_write_failures", 0) + 1


def _one_hot(futures: torch.Tensor, index: int) -> torch.Tensor:
    """``(K,)`` scores: 1 at index, 0 elsewhere, in the futures' float dtype (float32 for uint8 frames)."""
    dtype = futures.dtype if futures.is_floating_point() else torch.float32
    scores = torch.zeros(futures.shape[0], dtype=dtype, device=futures.device)
    scores[index] = 1.0
    return scores
