"""A scripted chat-completions server on the loopback interface, for the VLM reward's tests and benchmark.

It speaks the OpenAI-compatible ``POST /v1/chat/completions`` format that vLLM, Ollama and
llama.cpp's server speak, records every request it receives (body, headers, arrival time)
and answers from a script, so tests can check what the client really sends and drive each
failure path (malformed answer, slow reply, HTTP error) without a model.

Its ``usage`` figures are estimates, not a tokenizer's: image tokens follow Qwen2.5-VL's
rule (the image rounded to multiples of 28 px, one token per 28x28 patch, plus 2 markers)
and text tokens are counted as one per 4 characters, so the benchmark can say roughly
what a decision would cost on such a model.
"""

from __future__ import annotations

import base64
import json
import math
import threading
import time
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import cv2
import numpy as np

PATCH = 28  # Qwen2.5-VL: 14 px patches merged 2x2


@dataclass(frozen=True)
class Reply:
    """One scripted answer: the assistant's text, or an HTTP error status, after a delay."""

    content: str = "1"
    status: int = 200
    delay_s: float = 0.0
    raw: bytes | None = None  # send these bytes as the whole (JSON-typed) body instead: a broken server


@dataclass
class Received:
    """A request as the server saw it."""

    body: dict[str, Any]
    headers: dict[str, str]
    arrived: float  # time.perf_counter() at arrival
    size: int  # bytes of the request body

    def images(self) -> list[np.ndarray]:
        """The request's ``image_url`` data URLs decoded to RGB arrays ``(H, W, 3)`` uint8."""
        out = []
        for message in self.body.get("messages", []):
            content = message.get("content")
            for part in content if isinstance(content, list) else []:
                if part.get("type") == "image_url":
                    out.append(decode_data_url(part["image_url"]["url"]))
        return out

    def text(self) -> str:
        parts = []
        for message in self.body.get("messages", []):
            content = message.get("content")
            if isinstance(content, str):
                parts.append(content)
            for part in content if isinstance(content, list) else []:
                if part.get("type") == "text":
                    parts.append(part["text"])
        return "\n".join(parts)


def decode_data_url(url: str) -> np.ndarray:
    """``data:image/png;base64,...`` -> RGB ``(H, W, 3)`` uint8; raises ValueError if it is not a PNG."""
    head, _, payload = url.partition(",")
    if head != "data:image/png;base64":
        raise ValueError(f"not a base64 PNG data URL: {head[:40]!r}")
    raw = base64.b64decode(payload, validate=True)
    if not raw.startswith(b"\x89PNG\r\n\x1a\n"):
        raise ValueError("data URL payload is not a PNG")
    bgr = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_COLOR)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def image_tokens(height: int, width: int) -> int:
    """Qwen2.5-VL's count for one image: patches of the 28-px-rounded image, plus start/end markers."""
    h, w = max(PATCH, round(height / PATCH) * PATCH), max(PATCH, round(width / PATCH) * PATCH)
    return (h // PATCH) * (w // PATCH) + 2


def estimate_prompt_tokens(request: Received) -> int:
    images = request.images()
    return math.ceil(len(request.text()) / 4) + sum(image_tokens(*im.shape[:2]) for im in images)


class _Handler(BaseHTTPRequestHandler):
    server: _Server

    def do_POST(self) -> None:  # noqa: N802 (http.server's naming)
        raw = self.rfile.read(int(self.headers.get("Content-Length", 0)))
        body = json.loads(raw or b"{}")
        request = Received(body, {k.lower(): v for k, v in self.headers.items()}, time.perf_counter(), len(raw))
        if not self.path.rstrip("/").endswith("/chat/completions"):
            return self._send(404, {"error": {"message": f"no route {self.path}", "type": "not_found"}})
        reply = self.server.owner._next(request)
        if reply.delay_s:
            time.sleep(reply.delay_s)
        if reply.status != 200:
            return self._send(reply.status, {"error": {"message": "scripted failure", "type": "server_error"}})
        if reply.raw is not None:
            return self._send(200, reply.raw)
        prompt = estimate_prompt_tokens(request)
        completion = max(1, math.ceil(len(reply.content) / 4))
        self._send(200, {
            "id": f"chatcmpl-{len(self.server.owner.requests)}", "object": "chat.completion",
            "created": int(time.time()), "model": body.get("model", ""),
            "choices": [{"index": 0, "message": {"role": "assistant", "content": reply.content},
                         "finish_reason": "stop"}],
            "usage": {"prompt_tokens": prompt, "completion_tokens": completion,
                      "total_tokens": prompt + completion},
        })

    def _send(self, status: int, payload: dict[str, Any] | bytes) -> None:
        data = payload if isinstance(payload, bytes) else json.dumps(payload).encode()
        try:
            self.send_response(status)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data)
        except (BrokenPipeError, ConnectionResetError):
            pass  # the client gave up (a timeout test): nothing to answer

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 (http.server's signature)
        pass  # keep test output clean


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    block_on_close = False  # a slow scripted reply must not hold up shutdown
    owner: ScriptedChatServer

    def handle_error(self, request: Any, client_address: Any) -> None:
        pass  # a client that hung up mid-reply is expected here


class ScriptedChatServer:
    """Context manager: a chat-completions server on 127.0.0.1 (a free port) answering from ``script``.

    Replies are used in order; the last one repeats. ``requests`` holds every request received.
    """

    def __init__(self, script: list[Reply] | None = None) -> None:
        self.script = list(script or [Reply()])
        self.requests: list[Received] = []
        self._lock = threading.Lock()
        self._server: _Server | None = None

    def _next(self, request: Received) -> Reply:
        with self._lock:
            index = min(len(self.requests), len(self.script) - 1)
            self.requests.append(request)
            return self.script[index]

    @property
    def base_url(self) -> str:
        assert self._server is not None, "server not started"
        host, port = self._server.server_address[:2]
        return f"http://{host}:{port}/v1"

    def __enter__(self) -> ScriptedChatServer:
        self._server = _Server(("127.0.0.1", 0), _Handler)
        self._server.owner = self
        threading.Thread(target=self._server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True).start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
            self._server = None
