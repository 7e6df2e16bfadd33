"""The robot side of `sefa serve`: send an observation, get the action chunk back.

This file is the whole client and depends on numpy, msgpack and websockets only (no torch, no
other sefa module): copy it next to a robot script if sefa is not installed there.

    from client import PolicyClient          # or: from sefa_deploy.client import PolicyClient

    with PolicyClient("ws://127.0.0.1:8765") as policy:
        meta = policy.metadata()             # keys, shapes, dtypes, n_obs_steps, fps, ...
        while running:
            obs = {"keypoint": kp, "state": st}       # per key (To, *frame_shape), store units
            for a in policy.infer(obs)["action"]:    # (n_action_steps, Da), robot units
                robot.apply(a)

or let the server keep the observation history and hand out the chunk one step at a time
(receding horizon, Diffusion Policy's rollout loop): send the newest frame each control tick.

        policy.reset()                                 # a new episode
        while running:
            robot.apply(policy.step({"keypoint": kp_now, "state": st_now}))   # (Da,)

Protocol (version 1). Every request is one binary websocket message, a msgpack map with a
`type` and an optional `id` (any int or string, echoed back); every reply is one message:
`{"id": ..., "ok": true, ...}` or `{"id": ..., "ok": false, "error": "<what is wrong>"}`.

    {"type": "infer", "obs": {key: array}, "noise": array?}   -> action, action_pred, infer_ms
    {"type": "step", "obs": {key: one frame}}                 -> action (Da,), replanned
    {"type": "reset"}                                         -> the history is cleared
    {"type": "metadata"}                                      -> metadata (the export's JSON)
    {"type": "health"}                                        -> status, uptime_s, requests

Arrays travel as `{"__ndarray__": true, "dtype": "<f4", "shape": [...], "data": <bytes>}`, the
convention of openpi's msgpack_numpy, so that any language with msgpack can speak it. `infer`
takes (To, ...) per key or a batch (B, To, ...) and answers alike; `noise` is optional
(standard normal (horizon, Da) or (B, horizon, Da)): without it the server draws it.
"""

from __future__ import annotations

import inspect
import itertools
import socket
from typing import Any

import msgpack
import numpy as np
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

PROTOCOL_VERSION = 1
NUMERIC_KINDS = "biuf"  # bool, int, uint, float: what np.frombuffer may build from bytes


class MalformedMessage(ValueError):
    """A message that is not a well-formed protocol message (its text says why)."""


class PolicyServerError(RuntimeError):
    """The server answered with an error (the message names the problem), or the connection
    ended before it answered."""


# ---- the wire format (the server uses the same two functions)

def _encode(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind not in NUMERIC_KINDS:
            raise TypeError(f"cannot send an array of dtype {obj.dtype} (numbers only)")
        return {"__ndarray__": True, "dtype": obj.dtype.str, "shape": list(obj.shape),
                "data": np.ascontiguousarray(obj).tobytes()}
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"cannot send a {type(obj).__name__}")


def _decode(obj: dict) -> Any:
    if obj.get("__ndarray__") is not True:
        return obj
    try:
        dtype = np.dtype(obj["dtype"])
        shape = tuple(int(s) for s in obj["shape"])
        if dtype.kind not in NUMERIC_KINDS:
            raise ValueError(f"dtype {dtype} is not numeric")  # object arrays: never from bytes
        return np.frombuffer(obj["data"], dtype=dtype).reshape(shape)
    except (KeyError, TypeError, ValueError) as e:
        raise MalformedMessage(f"malformed array ({e})") from None


def pack(message: dict) -> bytes:
    return msgpack.packb(message, default=_encode, use_bin_type=True)


def unpack(data: bytes) -> Any:
    """Raises MalformedMessage on anything that is not a well-formed message."""
    if isinstance(data, str):
        raise MalformedMessage("text message; send binary msgpack")
    try:
        return msgpack.unpackb(data, object_hook=_decode, raw=False, strict_map_key=False)
    except MalformedMessage:
        raise
    except Exception as e:  # msgpack's own errors: ExtraData, FormatError, StackError, ...
        detail = f"{type(e).__name__}: {e}" if str(e) else type(e).__name__
        raise MalformedMessage(f"not a msgpack message ({detail})") from None


# ---- the client

class PolicyClient:
    """A connection to `sefa serve`. Blocking calls, one request in flight at a time; use one
    client per thread. Every call raises PolicyServerError with the server's message on an
    error reply."""

    def __init__(self, url: str = "ws://127.0.0.1:8765", *, timeout: float = 30.0,
                 open_timeout: float = 10.0):
        kwargs = {"legacy": True} if "legacy" in inspect.signature(connect).parameters else {}
        self.url, self.timeout = url, timeout
        # max_size=None: the server bounds what it accepts, the client takes what it is sent
        self._ws = connect(url, open_timeout=open_timeout, max_size=None, compression=None,
                           **kwargs)
        # small request / reply pairs: never wait for Nagle's algorithm
        self._ws.socket.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._ids = itertools.count(1)
        self._meta: dict | None = None

    def request(self, message: dict) -> dict:
        """Send one request and wait for its reply; returns the reply's fields."""
        message = {**message}
        message.setdefault("id", next(self._ids))
        try:
            self._ws.send(pack(message))
            reply = unpack(self._ws.recv(timeout=self.timeout))
        except ConnectionClosed as e:
            reason = e.rcvd.reason if e.rcvd is not None and e.rcvd.reason else str(e)
            raise PolicyServerError(f"connection to {self.url} closed: {reason}") from None
        except TimeoutError:
            raise PolicyServerError(f"no reply from {self.url} within {self.timeout:g} s") from None
        if not isinstance(reply, dict) or reply.get("id") != message["id"]:
            raise PolicyServerError(f"reply does not answer request {message['id']!r}")
        if not reply.get("ok"):
            raise PolicyServerError(str(reply.get("error", "error without a message")))
        return reply

    def metadata(self) -> dict:
        """The policy's inputs, outputs and timing (the export's metadata.json), cached."""
        if self._meta is None:
            self._meta = self.request({"type": "metadata"})["metadata"]
        return self._meta

    def health(self) -> dict:
        return self.request({"type": "health"})

    def infer(self, obs: dict[str, np.ndarray], noise: np.ndarray | None = None) -> dict:
        """obs: per key (To, *frame_shape) or (B, To, *frame_shape). Returns the reply:
        `action` (n_action_steps, Da) or (B, ...), `action_pred` (horizon, Da), `infer_ms`."""
        message: dict = {"type": "infer", "obs": obs}
        if noise is not None:
            message["noise"] = noise
        return self.request(message)

    def step(self, obs: dict[str, np.ndarray], noise: np.ndarray | None = None) -> np.ndarray:
        """Receding horizon: the newest frame per key in, the action to apply now out (Da,)."""
        message: dict = {"type": "step", "obs": obs}
        if noise is not None:  # used when this step predicts a new chunk
            message["noise"] = noise
        return self.request(message)["action"]

    def reset(self) -> None:
        """Forget the observation history and the queued actions (a new episode)."""
        self.request({"type": "reset"})

    def close(self) -> None:
        self._ws.close()

    def __enter__(self) -> "PolicyClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
