"""A video file encoded in a child process that a watchdog and Ctrl-C can stop.

PyAV's bundled SVT-AV1 (LeRobot's default codec) now and then stops for good inside
``encode`` (0 % CPU, waiting on a semaphore) while holding the interpreter: no timeout and no
Ctrl-C reaches a thread stuck there. So each video file is written by its own process (started
with ``spawn``: no copy of the parent's threads and locks), fed one episode at a time through a
pipe. The child reports every frame it has encoded; when it reports nothing for
``stall_timeout`` seconds it counts as stalled and is killed (SIGKILL, which needs no
cooperation). It ignores SIGINT: a terminal's Ctrl-C reaches the whole process group, and the
parent alone decides (it kills the child, and the conversion removes its temporary files). The
child asks the kernel to kill it when the parent dies, so a kill -9 of `sefa convert` leaves no
encoder behind.

Fault point ``convert.encode`` (store.journal.fault_point, in the child, before each frame):
``SEFA_FAULT=convert.encode:hang`` makes the encoder hang as SVT-AV1 does.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
from fractions import Fraction
from pathlib import Path

import numpy as np

from sefa_data.errors import SefaInputError

# --codec -> (PyAV encoder, LeRobot's codec name in info.json, options as LeRobot passes them)
CODECS = {
    "av1": ("libsvtav1", "av1", {"g": "2", "crf": "30", "preset": "12"}),
    "h264": ("h264", "h264", {"g": "2", "crf": "30"}),
    "hevc": ("hevc", "hevc", {"g": "2", "crf": "30", "x265-params": "log-level=error"}),
}
# Seconds without one frame encoded after which an encoder counts as stalled. Healthy encoders
# take milliseconds per frame (SVT-AV1 at preset 12 on 96x96 frames about 2 ms here), and tens
# of ms for camera frames, so a minute is far from a slow machine and still ends a hang.
DEFAULT_STALL_TIMEOUT = 60.0
# Starting the child (a fresh interpreter importing numpy and PyAV) is not encoding: on a loaded
# machine it takes seconds, so it gets its own allowance, whatever the stall timeout.
START_TIMEOUT = 120.0


class EncoderStalled(SefaInputError):
    """The encoder took no frame for longer than the stall timeout (or died)."""


class VideoProcess:
    """One video file, written by a child process (see the module docstring)."""

    def __init__(self, path: Path, key: str, codec: str, fps: float, stall_timeout: float):
        self.path, self.key, self.codec, self.fps = Path(path), key, codec, fps
        self.timeout = stall_timeout
        self.process = None
        self.conn = None
        self.frames = 0  # frames written to this file so far
        self.bytes = 0  # encoded bytes so far (the encoder holds frames: the file lags behind)

    def start(self, height: int, width: int) -> None:
        # SVT-AV1 prints its banner and configuration on stderr unless told to log errors only
        os.environ.setdefault("SVT_LOG", "1")
        ctx = multiprocessing.get_context("spawn")
        self.conn, child = ctx.Pipe()
        process = ctx.Process(target=_serve, name=f"sefa encoder {self.path.name}",
                              args=(child, str(self.path), self.codec, self.fps, height, width),
                              daemon=True)
        try:
            process.start()
        finally:  # interrupted while starting: the child reads EOF from the pipe and ends
            child.close()
        self.process = process
        self._wait("starting the encoder", max(self.timeout, START_TIMEOUT))

    def write(self, frames: np.ndarray, what: str) -> None:
        """Encode `frames` (N, H, W, 3 uint8); `what` names them in a stall's line."""
        if self.process is None:
            self.start(*frames.shape[1:3])
        frames = np.ascontiguousarray(frames)  # uint8, checked by the caller
        try:
            self.conn.send(("frames", frames.shape))
            self.conn.send_bytes(frames.reshape(-1).data)  # 1-D: send_bytes counts items
        except BrokenPipeError:  # the child is gone: _wait says how
            pass
        self._wait(what)

    def close(self, what: str = "finishing the video file") -> None:
        if self.process is None:
            return
        try:
            try:
                self.conn.send(("close", None))
            except BrokenPipeError:
                pass
            self._wait(what)
        finally:
            self.kill()

    def kill(self) -> None:
        """Stop the child at once (an error or an interrupt elsewhere); idempotent."""
        if self.process is not None:
            if self.process.is_alive():
                self.process.kill()
            self.process.join()
            self.process = None
        if self.conn is not None:
            self.conn.close()
            self.conn = None

    def _wait(self, what: str, timeout: float | None = None) -> None:
        """Until the child says it is done; every frame it encodes restarts the clock."""
        timeout = self.timeout if timeout is None else timeout
        while True:
            if not self.conn.poll(timeout):
                self.kill()
                raise EncoderStalled(
                    f"the {self.codec} encoder stalled on {what}: no frame encoded in "
                    f"{timeout:g} s (it was stopped and nothing was published; convert "
                    "again, or use --codec h264; --encoder-timeout sets this limit)",
                    key=self.key)
            try:
                kind, value = self.conn.recv()
            except EOFError:  # the child died (killed, out of memory, an encoder abort)
                self.process.join(5)
                code = self.process.exitcode
                self.kill()
                raise EncoderStalled(f"the {self.codec} encoder process died (exit code {code}) "
                                     f"on {what}; nothing was published", key=self.key) from None
            if kind == "frame":
                continue
            if kind == "error":
                self.kill()
                raise value
            self.frames, self.bytes = value
            return


def _serve(conn, path: str, codec: str, fps: float, height: int, width: int) -> None:
    """The child: open the file, then encode what the pipe brings until told to close."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _die_with_parent()
    try:
        import av

        from sefa_data.store.journal import fault_point

        encoder, _, options = CODECS[codec]
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        container = av.open(path, "w")
        stream = container.add_stream(encoder, rate=Fraction(fps).limit_denominator(1001),
                                      options=dict(options))
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        frames = size = 0
        conn.send(("done", (frames, size)))
        while True:
            kind, shape = conn.recv()
            if kind == "close":
                container.mux(stream.encode(None))
                container.close()
                conn.send(("done", (frames, size)))
                return
            batch = np.frombuffer(conn.recv_bytes(), np.uint8).reshape(shape)
            for img in batch:
                fault_point("convert.encode")
                # converted to the stream's yuv420p here, into buffers the frame owns: PyAV may
                # wrap the array without copying, and the encoder holds frames after this loop
                # has moved on
                frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(img), format="rgb24") \
                    .reformat(format="yuv420p")
                frame.pts = frames
                packets = stream.encode(frame)
                container.mux(packets)
                size += sum(p.size for p in packets)
                frames += 1
                conn.send(("frame", None))
            conn.send(("done", (frames, size)))
    except (EOFError, BrokenPipeError):  # the parent is gone or gave up on us
        return
    except BaseException as e:  # noqa: BLE001 (reported to the parent, which raises it)
        try:
            conn.send(("error", e))
        except Exception:  # an exception that does not pickle: its words
            conn.send(("error", RuntimeError(f"{type(e).__name__}: {e}")))


def _die_with_parent() -> None:
    """Linux: SIGKILL this process when its parent dies (prctl PR_SET_PDEATHSIG)."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG = 1
    except (OSError, AttributeError):  # not Linux: the closed pipe ends it at its next read
        pass
