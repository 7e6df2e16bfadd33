"""`sefa serve`: a policy behind a websocket, for a robot's control loop.

    serve(load_backend("distill"), host="127.0.0.1", port=8765)

Why websockets + msgpack (as openpi serves its policies): one persistent TCP connection and one
binary message each way per request, so a round trip costs a few hundred microseconds over
loopback with no per-request connection setup; numpy arrays travel as raw bytes with their dtype
and shape (no JSON, no base64); the client is a dozen lines on two well-kept pure-Python
libraries (`websockets`, `msgpack`) that a robot computer installs without a compiler, and any
language with a websocket and a msgpack library can speak it. gRPC (LeRobot's choice) needs
generated stubs and a protobuf schema per observation layout; ZeroMQ's REQ/REP sockets wedge
when a peer vanishes mid-request and have no handshake to reject a bad client cleanly.

Two protocols share the port, chosen per connection at the handshake:

* sefa's own (`sefa_deploy/client.py` documents it): the client offers the websocket
  subprotocol `sefa.v2`; requests carry a `type` and an `id`, errors are `ok: false` replies;
* openpi's (`openpi_client.websocket_client_policy.WebsocketClientPolicy`, unmodified): a
  client that offers no subprotocol. On connect the server sends one binary frame, msgpack of
  the metadata (openpi's client blocks until it arrives); then each message is the bare
  observation dict and each reply `{"actions": ..., "server_timing": {"infer_ms",
  "prev_total_ms"}}`; an error is a text frame with its one line (openpi's client raises
  RuntimeError with it) and the connection stays open.

  Why per connection and not per message: openpi's client sends nothing until the server has
  spoken, so the server must know before the first message whether to send the metadata frame,
  and a frame our client did not ask for would answer its first request. Nothing in openpi's
  handshake marks it and openpi's client cannot be changed; ours can, so ours is the one that
  says so, with the subprotocol, at no cost per message. Per connection
  also keeps each protocol's error form (text frame or `ok: false`) and its observation keys
  free of the other's words (an observation key named `type` stays an observation key).

  The openpi request: observation keys are the policy's (metadata `obs`) after the key map
  (`sefa serve --key-map observation/state=state`; `NAME=` drops a key, e.g. `prompt=`); a
  nested map's keys join with "/" (`{"images": {"cam": a}}` is `images/cam`). Each key is the
  (To, ...) history an `infer` request takes, or, for a policy with To = 1, just the frame. One
  observation, no batch axis: the reply's first axis is the step, as openpi's ActionChunkBroker
  slices it. An optional `noise` key (standard normal (horizon, Da) float) is the sampler's
  noise, so that a client can reproduce `Policy.predict_action(obs, noise=...)`; without it the
  server draws it from its seeded generator (`serve --seed`), as for sefa requests.
  `actions` is the reply's `action`, the n_action_steps (Da) to execute from the current frame
  on, not the whole predicted chunk: the chunk's first To - 1 steps belong to frames already
  past, and ActionChunkBroker executes every row it is given (run it with action_horizon <=
  n_action_steps, which the metadata frame carries). `prev_total_ms` is the previous request's
  time from its arrival to its reply sent (openpi's server also counts the wait for it).

Whatever the protocol, the arrays are openpi's msgpack_numpy encoding (bytes marker keys), and
`GET /healthz` (a plain HTTP request, no upgrade) is answered 200 "OK", as openpi's server does.

How the server stays up:

* every request is checked against the policy's metadata before it reaches the model: a missing
  or unexpected key, a wrong shape or dtype, NaN or Inf, a malformed message: the reply is
  `ok: false` (openpi: a text frame) with one line naming the key and the problem, and the
  connection stays open;
* a message larger than `max_message_bytes` cannot be answered without reading it, so
  websockets closes that connection with code 1009 and a reason naming the size and the limit;
  other connections are untouched. The package's client learns the limit from the metadata
  call and refuses such a request itself, with the same explanation;
* every action is checked before it is sent: an answer of the wrong shape or with NaN or Inf
  (a diverging sampler, a broken export) is an `ok: false` reply (openpi: a text frame) saying
  so and one log line; a robot never receives a non-finite command, whatever its protocol;
* inference runs off the event loop, on the policy's one worker thread (`Worker`: one model,
  one device, requests take turns in arrival order; torch and onnxruntime release the GIL while
  they compute). The loop stays free while a request runs, however slow the sampler (RK45 at a
  large batch, DDPM): other clients' health and metadata requests, new handshakes, keepalive
  pings and signals are answered at once. A connection's own requests are answered in order.
  At most `max_queue` requests wait behind the running one (a request beyond that gets a
  "server busy" error at once) and each gets its answer within `request_timeout_s`, its wait
  included, or a "no answer within" error (a request that has started runs on in the worker
  and its result is dropped: a thread cannot be interrupted). A client that disconnects
  mid-request only loses its reply;
* SIGINT and SIGTERM: no new inference (waiting requests get a "server is stopping" error), a
  wait of at most SHUTDOWN_GRACE_S (2 s; a second signal ends it) for the running request so
  that its client gets the answer, then every connection is closed with "going away" (1001) and
  `serve` returns: the process exits 0 and the port is free. A request still running then is
  abandoned (`sefa serve` exits without waiting for its thread).

Chunk execution (`step` requests): each connection has its own `Executor`
(sefa_model/policy/execution.py, the one owner of chunk execution, the same that `sefa eval
--env` runs): it keeps the last n_obs_steps frames of each key (the first frame of an episode
repeated until there are enough, as Diffusion Policy's MultiStepWrapper pads), decides when to
predict, draws the noise from the connection's generator (seeded with `serve --seed`, or with
a `reset` request's `seed`: the same seed gives the same actions as `sefa eval` at that seed)
and answers with this step's action. The execution (receding horizon, ACT's ensembling, a
choice among N samples by backward coherence or Bidirectional Decoding) is chosen per server
(`serve(execution=ExecutionSettings(...))`, `sefa serve --execution`); by default the one
recorded with the policy (metadata `execution`), else receding horizon over n_action_steps.
A step that predicts runs on the worker thread; every chunk is checked (shape, finite) and so
is the action before it is sent. The reply holds `action`, `replanned`, `queued` (the actions
left in the plan; ensemble: the predictions averaged) and `step_ms`, the server's time for
this step (checks, the prediction if one was due, the selection; not the network). `health`
reports the step times of the last STEP_WINDOW steps of all connections: `step_ms_p50`,
`step_ms_p99` and `step_jitter_ms`, the jitter defined as p99 - p50 (how much later than usual
a slow step answers: what a control loop's deadline must absorb). `reset` starts a new episode.
An openpi client sends no `step`s: it executes the chunks itself (openpi's
ActionChunkBroker), so --execution does not apply to it.

No authentication: bind to loopback (the default) or a network you trust.
"""

from __future__ import annotations

import asyncio
import collections
import http
import queue
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from websockets.asyncio.server import serve as ws_serve
from websockets.exceptions import ConnectionClosed

from sefa_deploy.client import PROTOCOL_VERSION, SUBPROTOCOL, MalformedMessage, pack, unpack
from sefa_model.policy.execution import ChunkShape, ExecutionSettings, Executor, default_settings

DEFAULT_PORT = 8765
DEFAULT_MAX_MESSAGE_BYTES = 16 * 2 ** 20
DEFAULT_MAX_QUEUE = 16  # several robots' control loops, each with one request in flight
# a one-step policy answers in ms and RK45 at batch 1 in about 1 s: a minute is a policy (or a
# batch) far too slow for any control loop, not a wait worth making a client sit through
DEFAULT_REQUEST_TIMEOUT_S = 60.0
SHUTDOWN_GRACE_S = 2.0
REQUEST_TYPES = ("infer", "step", "reset", "metadata", "health")
STEP_WINDOW = 10_000  # the steps `health`'s step-time percentiles cover


class RequestError(ValueError):
    """A bad request, or one the server cannot answer now: its message is the error reply."""


class RequestTimeout(RequestError):
    """No answer within the request timeout; `running`: the call goes on on the worker (it had
    started), its result to be dropped, rather than never to run."""

    def __init__(self, message: str, running: bool):
        super().__init__(message)
        self.running = running


class PolicyOutputError(RequestError):
    """The policy answered something that must not reach a robot (logged as well as replied)."""


# ---- checking a request against the metadata (pure functions)

def check_array(name: str, value, spec_shape: list[int], dtype: str) -> np.ndarray:
    """One input: a numeric array of `spec_shape` with or without a leading batch axis, cast to
    the declared dtype. Low-dim inputs take any float dtype; images exactly uint8. Returns a
    writable copy (decoded arrays view the read-only message; torch wants to own its input)."""
    if not isinstance(value, np.ndarray):
        raise RequestError(f"{name}: expected an array, got {type(value).__name__}")
    if dtype == "uint8":
        if value.dtype != np.uint8:
            raise RequestError(f"{name}: dtype {value.dtype}, expected uint8 (HWC image bytes)")
    elif value.dtype.kind != "f":
        raise RequestError(f"{name}: dtype {value.dtype}, expected a float type ({dtype})")
    shape = tuple(spec_shape)
    if value.shape == shape:
        value = value[None]
    elif value.ndim != len(shape) + 1 or value.shape[1:] != shape:
        want = ", ".join(map(str, shape))
        raise RequestError(f"{name}: shape {value.shape}, expected ({want}) or (B, {want})")
    if value.shape[0] == 0:
        raise RequestError(f"{name}: empty batch")
    if dtype == "uint8":
        return value.copy()
    # a sum is finite when every element is (one pass); only then is the exact test skipped
    if not np.isfinite(value.sum()) and not np.isfinite(value).all():
        raise RequestError(f"{name}: contains NaN or Inf")
    return np.array(value, dtype=np.float32)


def check_keys(obs, meta: dict) -> None:
    if not isinstance(obs, dict):
        raise RequestError("'obs' must be a map of observation key to array")
    if obs.keys() == meta["obs"].keys():
        return
    expected = list(meta["obs"])
    missing = [k for k in expected if k not in obs]
    if missing:
        raise RequestError(f"observation '{missing[0]}' missing (the policy needs: {', '.join(expected)})")
    extra = [str(k) for k in obs if k not in meta["obs"]]
    raise RequestError(f"unexpected observation '{extra[0]}' (the policy takes: {', '.join(expected)})")


def check_infer(request: dict, meta: dict) -> tuple[dict[str, np.ndarray], np.ndarray | None, bool]:
    """-> (obs with a batch axis, noise or None, whether the request had a batch axis)."""
    obs = request.get("obs")
    check_keys(obs, meta)
    out, first = {}, None
    for key, spec in meta["obs"].items():
        x = out[key] = check_array(f"observation '{key}'", obs[key], spec["shape"], spec["dtype"])
        batch = (x.shape[0], obs[key].ndim > len(spec["shape"]))  # (B, whether B was given)
        if first is None:
            first = batch
        elif batch != first:
            raise RequestError("observations disagree on the batch axis: " +
                               ", ".join(f"'{k}' {obs[k].shape}" for k in meta["obs"]))
    b, is_batched = first
    noise = request.get("noise")
    if noise is not None:
        shape = meta["noise"]["shape"]
        checked = check_array("noise", noise, shape, "float32")
        if checked.shape[0] != b or (noise.ndim == len(shape) + 1) != is_batched:
            want = f"(B={b}, {', '.join(map(str, shape))})" if is_batched else str(tuple(shape))
            raise RequestError(f"noise: shape {noise.shape}, the observations need {want}")
        noise = checked
    return out, noise, is_batched


def check_output(action, chunk, meta: dict, batch: int) -> None:
    """What the policy answered, before it is sent: the metadata's shapes, finite values."""
    wants = {"action": (batch, meta["n_action_steps"], meta["action_dim"]),
             "action_pred": (batch, *meta["noise"]["shape"])}
    for (name, want), value in zip(wants.items(), (action, chunk)):
        shape = getattr(value, "shape", type(value).__name__)
        if not isinstance(value, np.ndarray) or value.shape != want:
            raise PolicyOutputError(f"the policy produced '{name}' of shape {shape}, expected "
                                    f"{want}; nothing sent")
        if not np.isfinite(value).all():
            raise PolicyOutputError(f"the policy produced non-finite actions (NaN or Inf in "
                                    f"'{name}'); nothing sent")


# ---- the worker: inference off the event loop

class _Job:
    """One call for the worker thread and the future its request awaits on the loop."""

    __slots__ = ("fn", "args", "reply", "state")
    WAITING, RUNNING, CANCELLED = range(3)

    def __init__(self, fn, args: tuple, reply: asyncio.Future):
        self.fn, self.args, self.reply, self.state = fn, args, reply, _Job.WAITING


def torch_threads() -> int | None:
    """This thread's torch CPU thread count, None while torch is not loaded (an ONNX backend
    never imports it)."""
    torch = sys.modules.get("torch")
    return None if torch is None else torch.get_num_threads()


class Worker:
    """The policy's one thread and the bounded queue of requests waiting for it (the module
    docstring says why). `await worker.run(fn, *args)` is fn(*args) on that thread.

    A thread of its own fed by a SimpleQueue, not a ThreadPoolExecutor and `asyncio.wait_for`:
    the served call's profile (benchmarks/bench_serve.py) puts the hand-off and the hand-back
    among the largest costs outside the policy call, and most of their time is the two
    threads waking each other. So each direction is one step: a put that wakes the thread, and
    one `call_soon_threadsafe` as the thread's last act before it sleeps again (so that the
    loop, woken, finds the GIL free), which answers the request's future directly (no pool
    future, no done callbacks, no wait_for waiter between them)."""

    def __init__(self, *, max_queue: int = DEFAULT_MAX_QUEUE,
                 timeout_s: float = DEFAULT_REQUEST_TIMEOUT_S):
        self.max_queue, self.timeout_s = max_queue, timeout_s
        self.pending = 0  # submitted and not finished: the running call and those waiting
        self.replies: set[asyncio.Future] = set()
        self.stopping = False
        self._jobs: queue.SimpleQueue = queue.SimpleQueue()
        self._in_queue: set[_Job] = set()  # what `pending` counts (the loop's thread only)
        self._lock = threading.Lock()  # a job starts or is cancelled, never both
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._idle: asyncio.Future | None = None

    async def run(self, fn, *args):
        if self.stopping:
            raise RequestError("the server is stopping; request not run")
        if self.pending > self.max_queue:
            raise RequestError(f"server busy: the policy is running a request and "
                               f"{self.pending - 1} more wait for it (serve --max-queue "
                               f"{self.max_queue}); retry later")
        if self._thread is None:  # started by the first request, on the loop it answers
            self._loop = asyncio.get_running_loop()
            # a daemon: an idle worker never keeps a process alive (a held one: `serve`'s
            # caller decides, see serve())
            self._thread = threading.Thread(target=self._work, args=(torch_threads(),),
                                            name="sefa-policy", daemon=True)
            self._thread.start()
        job = _Job(fn, args, self._loop.create_future())
        self.pending += 1
        self._in_queue.add(job)
        self.replies.add(job.reply)
        self._jobs.put(job)
        timeout = asyncio.timeout(self.timeout_s)
        try:
            async with timeout:
                return await job.reply
        except TimeoutError:
            if not timeout.expired():
                raise  # the policy's own TimeoutError
            # still waiting: it never runs; running: it runs on, its result dropped
            waiting = self._cancel(job)
            raise RequestTimeout(f"no answer within {self.timeout_s:g} s (serve --request-timeout; "
                                 "the wait behind earlier requests included)",
                                 running=not waiting) from None
        finally:
            self.replies.discard(job.reply)

    def _work(self, threads: int | None) -> None:
        """The worker thread: jobs in arrival order until the None that stop() sends, at the
        torch thread count of the thread that started it (`threads`)."""
        if threads is not None:
            # torch.set_num_threads sets MKL's count for the calling thread only
            # (mkl_set_num_threads_local): a new thread's matrix products ran at MKL's default
            # and gave other last bits than the same policy in `sefa eval` (bid then chose
            # another sample); set again here, the worker computes as its starter does
            sys.modules["torch"].set_num_threads(threads)
        while (job := self._jobs.get()) is not None:
            with self._lock:
                if job.state == _Job.CANCELLED:
                    continue
                job.state = _Job.RUNNING
            try:
                result, error = job.fn(*job.args), None
            except BaseException as e:  # noqa: BLE001 - handed to the request, as a pool would
                result, error = None, e
            try:
                self._loop.call_soon_threadsafe(self._finished, job, result, error)
            except RuntimeError:  # the loop has closed: a job abandoned at shutdown
                pass
            del job, result, error  # hold nothing while asleep

    def _cancel(self, job: _Job) -> bool:
        """On the loop: a job that has not started never will. -> whether it was waiting."""
        with self._lock:
            if job.state != _Job.WAITING:
                return False
            job.state = _Job.CANCELLED
        self._done(job)
        return True

    def _finished(self, job: _Job, result, error: BaseException | None) -> None:
        """On the loop, called from the worker thread."""
        if not job.reply.done():  # a timed-out request's reply is cancelled already
            if error is not None:
                job.reply.set_exception(error)
            else:
                job.reply.set_result(result)
        self._done(job)

    def _done(self, job: _Job) -> None:
        self._in_queue.discard(job)
        self.pending -= 1
        if self.pending == 0 and self._idle is not None and not self._idle.done():
            self._idle.set_result(None)

    async def stop(self, grace_s: float, interrupted) -> int:
        """Refuse new work, cancel the waiting requests, and wait for the running one at most
        `grace_s` or until `interrupted` (an awaitable) is done. -> requests left running."""
        self.stopping = True
        for job in list(self._in_queue):
            if self._cancel(job) and not job.reply.done():
                job.reply.set_exception(RequestError("the server is stopping; request not run"))
        self._jobs.put(None)  # the thread ends after the running job
        interrupt = asyncio.ensure_future(interrupted)
        if self.pending:
            self._idle = asyncio.get_running_loop().create_future()
            await asyncio.wait([self._idle, interrupt], timeout=grace_s,
                               return_when=asyncio.FIRST_COMPLETED)
        interrupt.cancel()
        for reply in self.replies:  # wake their handlers: the connections close next
            if not reply.done():
                reply.set_exception(RequestError("the server stopped before the policy answered"))
        return self.pending


# ---- per-connection state for `step` requests

@dataclass
class Session:
    executor: Executor
    busy: bool = False  # a prediction of this connection is running on the worker

    def reset(self, seed: int | None = None) -> None:
        self.executor.reset(seed)


def check_step(request: dict, meta: dict, samples: int) -> tuple[dict[str, np.ndarray],
                                                                np.ndarray | None]:
    obs = request.get("obs")
    check_keys(obs, meta)
    frames = {}
    for key, spec in meta["obs"].items():
        x = check_array(f"observation '{key}'", obs[key], spec["shape"][1:], spec["dtype"])
        if x.shape[0] != 1 or obs[key].ndim != len(spec["shape"]) - 1:
            raise RequestError(f"observation '{key}': a step takes the newest frame only, shape "
                               f"({', '.join(map(str, spec['shape'][1:]))}), got {obs[key].shape}")
        frames[key] = x[0]
    noise = request.get("noise")
    if noise is not None:  # used only when this step predicts: one noise per sample
        shape = meta["noise"]["shape"]
        want = [tuple(shape)] if samples == 1 else []
        want.append((samples, *shape))
        if not isinstance(noise, np.ndarray) or noise.shape not in want:
            raise RequestError(f"noise: a step takes {' or '.join(map(str, want))} (this server "
                               f"draws {samples} sample(s) a decision), got "
                               f"{getattr(noise, 'shape', type(noise).__name__)}")
        noise = check_array("noise", noise.reshape(-1, *shape), shape, "float32")
    return frames, noise


def check_reset(request: dict) -> int | None:
    seed = request.get("seed")
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int)
                             or not 0 <= seed < 2 ** 63):
        raise RequestError(f"reset: seed must be an integer >= 0, got {seed!r}")
    return seed


# ---- openpi's request: the bare observation dict

def parse_key_map(pairs: list[str]) -> dict[str, str]:
    """`NAME=KEY` items -> {openpi name: policy key, or "" to drop it}. ValueError names the
    item that is not NAME=KEY."""
    out: dict[str, str] = {}
    for pair in pairs:
        name, sep, key = pair.partition("=")
        if not sep or not name or name in out:
            raise ValueError(f"'{pair}' is not NAME=KEY (an openpi observation name, '=', the "
                             "policy's key or nothing to drop it; each name once)")
        fed = next((n for n, k in out.items() if key and k == key), None)
        if fed is not None:  # else the last one named would silently win
            raise ValueError(f"'{pair}': the policy's '{key}' is already fed by '{fed}={key}' "
                             "(one observation name per key)")
        out[name] = key
    return out


def check_key_map(key_map: dict[str, str], meta: dict) -> None:
    for name, key in key_map.items():
        if key and key not in meta["obs"]:
            raise ValueError(f"'{name}={key}': the policy has no observation '{key}' (it takes: "
                             f"{', '.join(meta['obs'])})")


def _flatten(obs: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in obs.items():
        if not isinstance(key, str):
            raise RequestError(f"observation names are strings, got {key!r}")
        if isinstance(value, dict):
            out.update(_flatten(value, f"{prefix}{key}/"))
        else:
            out[prefix + key] = value
    return out


def check_openpi(request, meta: dict, key_map: dict[str, str]) -> tuple[dict[str, np.ndarray],
                                                                         np.ndarray | None]:
    """openpi's bare observation -> (obs and noise, each with a batch axis of 1; noise None when
    not given).
    The module docstring says what it may hold."""
    if not isinstance(request, dict):
        raise RequestError("an openpi request is a msgpack map of observation name to array, "
                           f"got {type(request).__name__}")
    flat = _flatten(request)
    noise = flat.pop("noise", None)
    obs: dict = {}
    for name, value in flat.items():
        key = key_map.get(name, name)
        if not key:
            continue
        if key in obs:
            raise RequestError(f"observation '{key}' given twice (the key map sends "
                               f"{' and '.join(repr(n) for n in flat if key_map.get(n, n) == key)} "
                               "to it)")
        obs[key] = value
    try:
        check_keys(obs, meta)
    except RequestError as e:
        raise RequestError(f"{e}; sefa serve --key-map NAME=KEY maps a client's names onto "
                           "these") from None
    for key, spec in meta["obs"].items():
        x = obs[key]
        # a To = 1 policy takes the bare frame, as openpi's policies do
        if spec["shape"][0] == 1 and isinstance(x, np.ndarray) and x.shape == tuple(spec["shape"][1:]):
            obs[key] = x[None]
    out, noise, batched = check_infer({"obs": obs, "noise": noise}, meta)
    if batched:
        want = ", ".join(f"'{k}' {tuple(s['shape'])}" for k, s in meta["obs"].items())
        raise RequestError(f"an openpi request is one observation, not a batch: {want}")
    return out, noise


# ---- the service: requests in, replies out

def served_execution(meta: dict, execution: ExecutionSettings | None,
                     source: str | None = None) -> ExecutionSettings:
    """What `step` requests run: `execution` when given (read from `source`, a file such as
    sefa.yaml, when it was not typed as options), else the one recorded with the policy
    (metadata `execution`), else receding horizon over n_action_steps; resolved and checked
    (ConfigError naming the option, or the file and its key)."""
    if execution is None and meta.get("execution"):
        execution, source = (ExecutionSettings.from_json(meta["execution"], source="metadata.json"),
                             "metadata.json")
    if execution is None:
        return default_settings(meta["n_action_steps"])
    return execution.resolved(meta["n_action_steps"], source=source)


class PolicyService:
    """Turns one decoded request into one reply."""

    def __init__(self, backend, *, seed: int = 0, max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
                 max_queue: int = DEFAULT_MAX_QUEUE,
                 request_timeout_s: float = DEFAULT_REQUEST_TIMEOUT_S,
                 execution: ExecutionSettings | None = None, weak=None,
                 key_map: dict[str, str] | None = None, log: Callable[[str], None] = print):
        """`execution`: how `step` requests execute chunks (None: the policy's recorded one,
        metadata `execution`, else receding horizon); `weak`: for bid, the weaker policy's
        backend (the same observations and noise shape)."""
        self.backend, self.meta, self.log = backend, backend.metadata, log
        self.key_map = dict(key_map or {})
        check_key_map(self.key_map, self.meta)
        self.shape = ChunkShape.of(self.meta)
        self.execution = served_execution(self.meta, execution)
        self.weak = weak
        if self.execution.mode == "bid" and weak is None:
            raise ValueError(f"--weak: {self.execution.label} needs the weaker policy "
                             f"({self.execution.weak}) loaded")
        self.seed = seed
        self.step_ms: collections.deque = collections.deque(maxlen=STEP_WINDOW)
        self.max_message_bytes = max_message_bytes
        self.worker = Worker(max_queue=max_queue, timeout_s=request_timeout_s)
        self.rng = np.random.default_rng(seed)
        self.started = time.monotonic()
        self.counts = {"requests": 0, "errors": 0, "clients": 0}

    async def _predict(self, obs: dict[str, np.ndarray], noise: np.ndarray | None) -> dict:
        if noise is None:  # drawn here, on the loop: one generator, one thread
            b = next(iter(obs.values())).shape[0]
            noise = self.rng.standard_normal((b, *self.meta["noise"]["shape"]), dtype=np.float32)
        return await self.worker.run(self._infer, obs, noise)

    def _infer(self, obs: dict[str, np.ndarray], noise: np.ndarray) -> dict:
        """On the worker thread."""
        start = time.perf_counter()
        action, chunk = self.backend(obs, noise)
        infer_ms = (time.perf_counter() - start) * 1e3
        check_output(action, chunk, self.meta, noise.shape[0])
        return {"action": action, "action_pred": chunk, "infer_ms": infer_ms}

    async def handle(self, request, session: Session) -> dict:
        if not isinstance(request, dict):
            raise RequestError("a request is a msgpack map with a 'type'")
        kind = request.get("type")
        if kind == "infer":
            obs, noise, batched = check_infer(request, self.meta)
            out = await self._predict(obs, noise)
            if not batched:
                out["action"], out["action_pred"] = out["action"][0], out["action_pred"][0]
            return out
        if kind == "step":
            return await self._step(request, session)
        if kind == "reset":
            seed = check_reset(request)
            if session.busy:
                raise RequestError("this connection's previous prediction is still running; "
                                   "send the reset again later")
            session.reset(seed)
            return {}
        if kind == "metadata":
            return {"metadata": self.meta, "protocol": PROTOCOL_VERSION,
                    "max_message_bytes": self.max_message_bytes}
        if kind == "health":
            return {"status": "ok", "uptime_s": time.monotonic() - self.started,
                    "backend": self.backend.name, "device": str(self.backend.device),
                    "protocol": PROTOCOL_VERSION, **self.counts, **self.step_stats()}
        raise RequestError(f"unknown request type {kind!r} (one of: {', '.join(REQUEST_TYPES)})")

    async def _step(self, request: dict, session: Session) -> dict:
        start = time.perf_counter()
        ex = session.executor
        frames, noise = check_step(request, self.meta, ex.settings.samples)
        if session.busy:  # only after a step's answer timed out while it was predicting
            raise RequestError("this connection's previous prediction is still running; "
                               "send the step again later")
        if ex.steps_to_decision == 0:
            action = await self._decide(session, frames, noise)
        else:
            action = ex.action(frames)
        if not np.isfinite(action).all():  # the chunks were checked; this is the last word
            raise PolicyOutputError("the action to send is not finite (NaN or Inf); nothing sent")
        step_ms = (time.perf_counter() - start) * 1e3
        self.step_ms.append(step_ms)
        return {"action": action, "replanned": ex.replanned, "queued": ex.count,
                "step_ms": step_ms}

    async def _decide(self, session: Session, frames: dict, noise) -> np.ndarray:
        """A step that predicts, on the worker. The connection is busy until the prediction
        ends, not until its answer times out: a prediction that runs on after its timeout
        still moves the executor (the step counts; its action is dropped), and no other step or
        reset of the connection may touch the executor meanwhile."""
        def decide():
            try:
                return session.executor.action(frames, noise)
            finally:
                session.busy = False  # on the worker thread, as the prediction ends
        session.busy = True
        try:
            return await self.worker.run(decide)
        except RequestTimeout as e:
            if not e.running:  # it never will; a running one clears `busy` as it ends
                session.busy = False
            raise
        except BaseException:
            session.busy = False  # refused before it ran (busy server, stopping), or failed
            raise

    def _chunks(self, backend):
        """`backend` as the executor samples it, on the worker thread: every chunk checked."""
        def sample(obs: dict[str, np.ndarray], noise: np.ndarray, generator) -> np.ndarray:
            action, chunk = backend(obs, noise, generator=generator)
            check_output(action, chunk, self.meta, noise.shape[0])
            return chunk
        return sample

    def new_session(self) -> Session:
        weak = None if self.weak is None else self._chunks(self.weak)
        return Session(Executor(self.execution, self._chunks(self.backend), self.shape,
                                seed=self.seed, weak=weak))

    def step_stats(self) -> dict:
        """Percentiles of the recent `step` times (the module docstring defines jitter)."""
        ex = self.execution
        out = {"execution": ex.mode, "replan_every": ex.replan_every, "samples": ex.samples,
               "execution_label": ex.label, "steps": len(self.step_ms)}
        if self.step_ms:
            p50, p99 = np.percentile(np.fromiter(self.step_ms, float), [50, 99])
            out.update(step_ms_p50=float(p50), step_ms_p99=float(p99),
                       step_jitter_ms=float(p99 - p50))
        return out

    def _error(self, e: Exception, peer: str) -> str:
        """The one line a failed request is answered with (logged too when it is the server's
        side that failed)."""
        self.counts["errors"] += 1
        if isinstance(e, PolicyOutputError):
            self.log(f"client {peer}: {e}")
            return str(e)
        if isinstance(e, (RequestError, MalformedMessage)):
            return str(e)
        # a failure inside the model: report it, keep serving
        self.log(f"client {peer}: inference failed: {type(e).__name__}: {e}")
        return f"inference failed: {type(e).__name__}: {e}"

    async def connection(self, ws) -> None:
        """One client: requests answered in order until it leaves."""
        peer = _peer(ws)
        openpi = ws.subprotocol != SUBPROTOCOL
        self.counts["clients"] += 1
        self.log(f"client {peer} connected" + (" (openpi protocol)" if openpi else ""))
        try:
            await (self._openpi(ws, peer) if openpi else self._sefa(ws, peer))
        except ConnectionClosed:
            pass  # it left mid-request: its reply has no one to go to
        finally:
            self.counts["clients"] -= 1
            code = ws.close_code
            self.log(f"client {peer} disconnected" + (f" ({code}: {ws.close_reason})"
                                                      if code not in (None, 1000, 1001) else ""))

    async def _sefa(self, ws, peer: str) -> None:
        session = self.new_session()
        async for message in ws:
            self.counts["requests"] += 1
            request_id = None
            try:
                request = unpack(message)
                request_id = request.get("id") if isinstance(request, dict) else None
                reply = {"id": request_id, "ok": True, **await self.handle(request, session)}
            except Exception as e:
                reply = {"id": request_id, "ok": False, "error": self._error(e, peer)}
            await ws.send(pack(reply))

    def openpi_metadata(self) -> dict:
        """The frame an openpi client gets on connect (its get_server_metadata())."""
        return {**self.meta, "max_message_bytes": self.max_message_bytes,
                "key_map": self.key_map}

    async def _openpi(self, ws, peer: str) -> None:
        await ws.send(pack(self.openpi_metadata()))
        prev_total_ms = None
        async for message in ws:
            start = time.monotonic()
            self.counts["requests"] += 1
            try:
                obs, noise = check_openpi(unpack(message), self.meta, self.key_map)
                out = await self._predict(obs, noise)
            except Exception as e:
                # a text frame: openpi's client raises RuntimeError with it; unlike openpi's
                # server we keep the connection, as for our own clients
                await ws.send(self._error(e, peer))
                continue
            timing = {"infer_ms": out["infer_ms"]}
            if prev_total_ms is not None:  # as openpi's: the last request's, its send included
                timing["prev_total_ms"] = prev_total_ms
            await ws.send(pack({"actions": out["action"][0], "server_timing": timing}))
            prev_total_ms = (time.monotonic() - start) * 1e3


def _health_check(connection, request):
    """`GET /healthz` without an upgrade: 200, as openpi's server answers its load balancers."""
    if request.path == "/healthz" and "upgrade" not in request.headers.get("Connection", "").lower():
        return connection.respond(http.HTTPStatus.OK, "OK\n")
    return None


def _select_subprotocol(connection, offered):
    """Our client offers SUBPROTOCOL; openpi's offers none and gets the openpi protocol."""
    return SUBPROTOCOL if SUBPROTOCOL in offered else None


def _peer(ws) -> str:
    try:
        host, port = ws.remote_address[:2]
        return f"{host}:{port}"
    except (TypeError, ValueError):
        return "?"


async def run_server(service: PolicyService, host: str, port: int, *,
                     on_ready: Callable[[str, int], None] = lambda h, p: None) -> int:
    """Serve until SIGINT or SIGTERM; then stop as the module docstring says and return the
    number of requests abandoned (still running in the worker, 0 or 1)."""
    loop = asyncio.get_running_loop()
    signals: asyncio.Queue[int] = asyncio.Queue()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, signals.put_nowait, sig)
    try:
        # no keepalive pings of its own (a client's pings are answered): a robot script may sit
        # idle between episodes without reading, and a vanished client is noticed when its
        # socket closes or its reply cannot be sent;
        # for the same reason a closing handshake is not awaited for long (close_timeout)
        async with ws_serve(service.connection, host, port, max_size=service.max_message_bytes,
                            compression=None, ping_interval=None, close_timeout=1.0,
                            subprotocols=[SUBPROTOCOL], select_subprotocol=_select_subprotocol,
                            process_request=_health_check) as server:
            sock = next(iter(server.sockets))
            on_ready(*sock.getsockname()[:2])
            sig = await signals.get()
            service.log(f"{signal.Signals(sig).name}: closing connections")
            abandoned = await service.worker.stop(SHUTDOWN_GRACE_S, signals.get())
            if abandoned:
                service.log(f"a request still running after {SHUTDOWN_GRACE_S:g} s is abandoned")
            server.close()  # stop accepting; open connections get 1001 going away
            await server.wait_closed()
        return abandoned
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)


def serve(backend, host: str = "127.0.0.1", port: int = DEFAULT_PORT, *, seed: int = 0,
          max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES, max_queue: int = DEFAULT_MAX_QUEUE,
          request_timeout_s: float = DEFAULT_REQUEST_TIMEOUT_S,
          execution: ExecutionSettings | None = None, weak=None, key_map: dict[str, str] | None = None,
          log: Callable[[str], None] = print,
          on_ready: Callable[[str, int], None] | None = None) -> int:
    """Blocking: serve `backend` until SIGINT/SIGTERM. Port 0 picks a free port (on_ready
    gets the real one). Returns the number of requests abandoned at the stop: their thread
    is still inside the policy (a daemon thread, but an interpreter tearing its modules down
    under a running native call is not safe), so a caller that must exit now leaves with
    os._exit (as `sefa serve` does)."""
    service = PolicyService(backend, seed=seed, max_message_bytes=max_message_bytes,
                            max_queue=max_queue, request_timeout_s=request_timeout_s,
                            execution=execution, weak=weak, key_map=key_map, log=log)
    ready = on_ready or (lambda h, p: log(f"serving on ws://{h}:{p}"))
    main = run_server(service, host, port, on_ready=ready)
    try:
        import uvloop  # optional (the `deploy` extra): a faster event loop, ~0.05 ms per request
    except ImportError:
        return asyncio.run(main)
    return uvloop.run(main)
