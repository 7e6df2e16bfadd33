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

Protocol (version 2). The client offers the websocket subprotocol `sefa.v2` in its handshake;
a connection that offers none is an openpi client's (`sefa_deploy/server.py` says how the two
share a port). Every request is one binary websocket message, a msgpack map with a `type` and
an optional `id` (any int or string, echoed back); every reply is one message:
`{"id": ..., "ok": true, ...}` or `{"id": ..., "ok": false, "error": "<what is wrong>"}`.

    {"type": "infer", "obs": {key: array}, "noise": array?}   -> action, action_pred, infer_ms
    {"type": "step", "obs": {key: one frame}, "noise": array?}
                                                    -> action (Da,), replanned, queued
    {"type": "reset"}                               -> the history and the queue are cleared
    {"type": "metadata"}                            -> metadata (the export's JSON),
                                                       max_message_bytes, protocol
    {"type": "health"}                              -> status, uptime_s, requests, errors,
                                                       clients, backend, device

Arrays travel exactly as openpi's msgpack_numpy writes them (openpi-client 0.1.2): the map
`{b"__ndarray__": True, b"data": <bytes>, b"dtype": "<f4", b"shape": [...]}` whose marker keys
are msgpack bin (bytes), not str; a numpy scalar is `{b"__npgeneric__": True, b"data": value,
b"dtype": "<f4"}`. So openpi's own `msgpack_numpy.unpackb` reads our messages and ours read its
messages, and any language with msgpack can speak it. `infer` takes (To, ...) per key or a batch
(B, To, ...) and answers alike; `noise` is optional (standard normal (horizon, Da) or
(B, horizon, Da)): without it the server draws it. Version 1 (before issue 24) wrote the marker
keys as str and offered no subprotocol: a version-1 copy of this file cannot talk to a version-2
server (copy this file again).
"""

from __future__ import annotations

import itertools
import socket
from typing import Any

import msgpack
import numpy as np
from websockets.client import ClientProtocol
from websockets.frames import Opcode
from websockets.protocol import State
from websockets.uri import parse_uri

PROTOCOL_VERSION = 2
SUBPROTOCOL = "sefa.v2"  # offered in the handshake: what tells our client from openpi's
NUMERIC_KINDS = "biuf"  # bool, int, uint, float: what np.frombuffer may build from bytes


class MalformedMessage(ValueError):
    """A message that is not a well-formed protocol message (its text says why)."""


class PolicyServerError(RuntimeError):
    """The server answered with an error (the message names the problem), or the connection
    ended before it answered."""


# ---- the wire format (the server uses the same two functions)

def _encode(obj: Any) -> Any:
    """openpi's msgpack_numpy.pack_array, with numbers only (no str, bytes or datetime arrays
    either: nothing a policy takes or answers)."""
    if isinstance(obj, (np.ndarray, np.generic)):
        if obj.dtype.kind not in NUMERIC_KINDS:
            raise TypeError(f"cannot send an array of dtype {obj.dtype} (numbers only)")
        if isinstance(obj, np.ndarray):
            # tobytes() is C order whatever the array's layout
            return {b"__ndarray__": True, b"data": obj.tobytes(), b"dtype": obj.dtype.str,
                    b"shape": obj.shape}
        return {b"__npgeneric__": True, b"data": obj.item(), b"dtype": obj.dtype.str}
    raise TypeError(f"cannot send a {type(obj).__name__}")


_DTYPES: dict[str, np.dtype] = {}  # dtype strings seen, checked once: a request's hot path


def _dtype(name) -> np.dtype:
    dtype = _DTYPES.get(name) if isinstance(name, str) else None
    if dtype is None:
        dtype = np.dtype(name)
        if dtype.kind not in NUMERIC_KINDS:  # object arrays: never from bytes
            raise ValueError(f"dtype {dtype} is not numeric")
        if len(_DTYPES) < 64:
            _DTYPES[name] = dtype
    return dtype


def _decode(obj: dict) -> Any:
    """openpi's msgpack_numpy.unpack_array, refusing what it would not have sent or what does
    not add up (a size that does not match the bytes, a non-numeric dtype)."""
    try:
        if b"__ndarray__" in obj:
            # reshape refuses a size that does not match the bytes, and anything but integers
            return np.frombuffer(obj[b"data"], dtype=_dtype(obj[b"dtype"])).reshape(obj[b"shape"])
        if b"__npgeneric__" in obj:
            return _dtype(obj[b"dtype"]).type(obj[b"data"])
    except (KeyError, TypeError, ValueError, OverflowError) as e:
        raise MalformedMessage(f"malformed array ({e})") from None
    return obj


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
    error reply, and when the connection ends.

    The websocket protocol is websockets' own (its Sans-I/O `ClientProtocol`: handshake,
    framing, close codes) driven over a plain blocking socket in this thread: one send and one
    receive per request, no background thread to hand the reply over (that hand-off costs
    about 0.07 ms per request, a quarter of the server's latency budget)."""

    def __init__(self, url: str = "ws://127.0.0.1:8765", *, timeout: float = 30.0,
                 open_timeout: float = 10.0):
        self.url, self.timeout = url, timeout
        uri = parse_uri(url)
        # max_size=None: the server bounds what it accepts, the client takes what it is sent
        self._protocol = ClientProtocol(uri, subprotocols=[SUBPROTOCOL], max_size=None)
        try:
            sock = socket.create_connection((uri.host, uri.port), timeout=open_timeout)
        except OSError as e:
            raise PolicyServerError(f"cannot connect to {url}: {e.strerror or e}") from None
        # small request / reply pairs: never wait for Nagle's algorithm
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        if uri.secure:
            import ssl

            sock = ssl.create_default_context().wrap_socket(sock, server_hostname=uri.host)
        self._sock = sock
        self._protocol.send_request(self._protocol.connect())
        self._flush()
        try:
            while self._protocol.state is State.CONNECTING:
                self._receive(open_timeout)
                self._protocol.events_received()  # the handshake response
        except (TimeoutError, socket.timeout):
            self._sock.close()
            raise PolicyServerError(f"no websocket handshake from {url} within "
                                    f"{open_timeout:g} s") from None
        if self._protocol.handshake_exc is not None:
            self._sock.close()
            raise PolicyServerError(f"websocket handshake with {url} failed: "
                                    f"{self._protocol.handshake_exc}")
        if self._protocol.subprotocol != SUBPROTOCOL:
            self._sock.close()
            raise PolicyServerError(f"{url} does not speak sefa protocol {PROTOCOL_VERSION} (no "
                                    f"'{SUBPROTOCOL}' subprotocol: an older `sefa serve`, or an "
                                    "openpi server?)")
        self._sock.settimeout(timeout)
        self._ids = itertools.count(1)
        self._meta: dict | None = None
        self._limit: int | None = None
        self.metadata()  # what the policy takes, and the server's message size limit

    # -- the socket

    def _flush(self) -> None:
        for data in self._protocol.data_to_send():
            try:
                if data:
                    self._sock.sendall(data)
                else:  # SEND_EOF: the protocol asks for a half-close
                    self._sock.shutdown(socket.SHUT_WR)
            except OSError:
                self._protocol.receive_eof()
                return

    def _receive(self, timeout: float | None = None) -> None:
        if timeout is not None:
            self._sock.settimeout(timeout)
        try:
            data = self._sock.recv(1 << 16)
        except (TimeoutError, socket.timeout):
            raise
        except OSError:  # reset by the peer
            data = b""
        if data:
            self._protocol.receive_data(data)
        else:
            self._protocol.receive_eof()
        self._flush()  # pongs and the closing handshake go out at once

    def _closed_error(self) -> PolicyServerError:
        close = self._protocol.close_rcvd
        reason = (f"{close.code}: {close.reason}" if close is not None and close.reason
                  else f"code {close.code}" if close is not None else "no close frame")
        return PolicyServerError(f"connection to {self.url} closed ({reason})")

    def _recv_message(self) -> bytes:
        parts: list[bytes] = []
        while True:
            for event in self._protocol.events_received():
                if event.opcode in (Opcode.BINARY, Opcode.TEXT, Opcode.CONT):
                    parts.append(event.data)
                    if event.fin:
                        data = b"".join(parts)
                        return data.decode() if event.opcode is Opcode.TEXT else data
            if self._protocol.state is State.CLOSED or self._protocol.close_rcvd is not None:
                raise self._closed_error()
            try:
                self._receive()
            except (TimeoutError, socket.timeout):
                self.close()  # a late reply would answer the wrong request: start over
                raise PolicyServerError(f"no reply from {self.url} within {self.timeout:g} s; "
                                        "the connection is closed") from None

    def request(self, message: dict) -> dict:
        """Send one request and wait for its reply; returns the reply's fields."""
        message = {**message}
        message.setdefault("id", next(self._ids))
        data = pack(message)
        if self._limit is not None and len(data) > self._limit:
            raise PolicyServerError(f"request of {len(data)} bytes exceeds the server's limit of "
                                    f"{self._limit} bytes (sefa serve --max-message-mb)")
        if self._protocol.state is not State.OPEN:
            raise self._closed_error()
        self._protocol.send_binary(data)
        self._flush()
        reply = unpack(self._recv_message())
        if not isinstance(reply, dict) or reply.get("id") != message["id"]:
            raise PolicyServerError(f"reply does not answer request {message['id']!r}")
        if not reply.get("ok"):
            raise PolicyServerError(str(reply.get("error", "error without a message")))
        return reply

    def metadata(self) -> dict:
        """The policy's inputs, outputs and timing (the export's metadata.json), cached."""
        if self._meta is None:
            reply = self.request({"type": "metadata"})
            self._meta, self._limit = reply["metadata"], reply.get("max_message_bytes")
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
        """The closing handshake when the connection is open, then the socket is closed."""
        if self._protocol.state is State.OPEN:
            self._protocol.send_close(1000)
            self._flush()
            try:
                self._sock.settimeout(1.0)
                while self._protocol.state is not State.CLOSED:
                    self._receive()
            except OSError:
                pass
        self._sock.close()

    def __enter__(self) -> "PolicyClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
