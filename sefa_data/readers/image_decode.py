"""Camera messages to RGB uint8 arrays, in the reader or in worker processes.

A `sensor_msgs/Image` or `CompressedImage` is first reduced, in the reader, to an `Encoded`
(plain bytes and numbers, so that it pickles), and `decode` turns that into an RGB uint8
(height, width, 3) array with Pillow, resizing bilinearly when the size differs. Both the
reader's own decoding and the worker processes of `DecodePool` call the same `decode_batch`, so
a store's bytes do not depend on where its frames were decoded.

Why processes: a 96 x 96 JPEG costs about 130 us in Pillow, half of it Python (header parsing,
the load loop, the copy to numpy) that holds the GIL, while the reader itself is Python
(rosbags) that never lets go of it; decode threads would mostly wait for the GIL (measured:
two threads decoded fewer JPEGs per second than one). Workers pay for themselves only on idle
cores: each frame crosses a pipe twice, so a busy machine is better off decoding in the reader.

This module imports only numpy and Pillow: worker processes start from it.
"""

from __future__ import annotations

import io
import multiprocessing
import os
import threading
from collections import deque
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Any, NamedTuple

import numpy as np
from PIL import Image

from sefa_data.errors import SefaInputError

# encoding -> (channels, the channels that give RGB: a slice keeps the copy a plain strided one;
# None repeats the one grey channel)
_RAW_LAYOUTS = {"rgb8": (3, slice(0, 3)), "bgr8": (3, slice(2, None, -1)),
                "rgba8": (4, slice(0, 3)), "bgra8": (4, slice(2, None, -1)), "mono8": (1, None)}
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")


class Encoded(NamedTuple):
    """One image message as it was sent, without the message object."""

    data: Any  # bytes (compressed) or a uint8 array (raw)
    format: str = ""  # compressed: the message's format text, e.g. "jpeg"
    encoding: str = ""  # raw: rgb8, bgr8, ...
    height: int = 0
    width: int = 0
    step: int = 0


def encoded(msg: Any, kind: str) -> Encoded:
    """The message's image; `kind` is its type name (sensor_msgs/msg/Image, ...)."""
    if kind.endswith("/CompressedImage"):
        return Encoded(bytes(msg.data), format=msg.format)
    if kind.endswith("/Image"):
        return Encoded(np.asarray(msg.data, dtype=np.uint8), encoding=msg.encoding,
                       height=msg.height, width=msg.width, step=msg.step)
    raise SefaInputError(f"image_size is set but the topic carries {kind}, not "
                         f"{' or '.join(IMAGE_TYPES)}")


def raw_rgb(image: Encoded) -> np.ndarray:
    """A raw image as an RGB uint8 (H, W, 3) C-contiguous array of its own (never a view of the
    message, which may share a buffer with the rest of the recording)."""
    encoding = image.encoding.lower()
    if encoding not in _RAW_LAYOUTS:
        raise SefaInputError(f"image encoding '{image.encoding}' is not supported (supported: "
                             f"{', '.join(_RAW_LAYOUTS)})")
    channels, rgb = _RAW_LAYOUTS[encoding]
    data, height, width, step = image.data, image.height, image.width, image.step
    if data.size != height * step or step < width * channels:
        raise SefaInputError(f"image data has {data.size} bytes; {height} rows of step "
                             f"{step} for width {width} x {channels} channels expected")
    rows = data.reshape(height, step)[:, :width * channels]  # drop row padding
    pixels = rows.reshape(height, width, channels)
    if rgb is None:
        return np.repeat(pixels, 3, axis=2)
    return np.array(pixels[:, :, rgb], order="C")  # one copy


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 200 else text[:197] + "..."


def decode(image: Encoded, height: int, width: int) -> np.ndarray:
    """RGB uint8 (height, width, 3), resized bilinearly when the image has another size."""
    if isinstance(image.data, bytes):
        try:
            with Image.open(io.BytesIO(image.data)) as im:
                im.load()
                # convert() of an RGB image is a copy; camera JPEGs decode to RGB
                pil = im if im.mode == "RGB" else im.convert("RGB")
        except Exception as e:  # Pillow's decoders raise many types on bad bytes
            raise SefaInputError(f"cannot decode the compressed image ({image.format}): "
                                 f"{_one_line(e)}") from None
    else:
        rgb = raw_rgb(image)
        if rgb.shape[:2] == (height, width):
            return rgb
        pil = Image.fromarray(rgb)
    if pil.size != (width, height):
        pil = pil.resize((width, height), Image.Resampling.BILINEAR)
    return np.asarray(pil, dtype=np.uint8)


def decode_batch(images: list[Encoded], height: int, width: int
                 ) -> tuple[np.ndarray | None, tuple[int, str] | None]:
    """(frames, None), or (None, (index in the batch, what is wrong)) at the first image that
    does not decode. The error travels as plain values: it may cross a process boundary."""
    out = np.empty((len(images), height, width, 3), np.uint8)
    for i, image in enumerate(images):
        try:
            out[i] = decode(image, height, width)
        except SefaInputError as e:
            return None, (i, e.what)
    return out, None


# --- the pool ------------------------------------------------------------------------------------

BATCH = 64  # images per task: enough to pay for the hand-over, few enough to keep workers fed
# Fewer image messages than this are decoded in the reader alone: the first start of workers
# in a process takes about 0.3 s (a fork server that imports numpy, Pillow and the main
# module), in which the reader decodes some 2,000 small JPEGs itself.
MIN_IMAGES_FOR_POOL = 2000


def default_workers() -> int:
    """Worker processes for image decoding: one per CPU the process may use, less the one that
    runs the reader (which decodes too when the workers are behind)."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cpus = os.cpu_count() or 1
    return max(0, min(cpus - 1, 8))


class _Done:
    """A batch the reader decoded itself, with a Future's `result()`."""

    def __init__(self, value: Any):
        self.value = value

    def result(self) -> Any:
        return self.value

    def done(self) -> bool:
        return True


class DecodePool:
    """Decodes batches in `workers` processes, and in the calling thread while the workers are
    starting or already have two batches each (so that the reader never waits for them and
    their queue stays short). With 0 workers every batch is decoded in the calling thread.
    Use as a context manager."""

    def __init__(self, workers: int):
        self.workers = workers
        self._executor: ProcessPoolExecutor | None = None
        self._ready = threading.Event()
        self._queued: deque[Future] = deque()
        self._starter: threading.Thread | None = None
        if workers > 0:
            # Starting takes a fraction of a second (a first fork server start, the imports of
            # every worker); the reader decodes meanwhile instead of waiting in `submit`.
            self._starter = threading.Thread(target=self._start, name="sefa-decode-start",
                                             daemon=True)
            self._starter.start()

    def _start(self) -> None:
        executor = ProcessPoolExecutor(self.workers, mp_context=_context())
        self._executor = executor
        try:
            # a pool starts a worker per submitted task, up to `workers`
            for started in [executor.submit(int) for _ in range(self.workers)]:
                started.result()
        except Exception:  # no workers on this system: the reader decodes every batch
            return
        self._ready.set()

    def __enter__(self) -> "DecodePool":
        return self

    def __exit__(self, *exc) -> None:
        if self._starter is not None:
            self._starter.join()
        if self._executor is not None:
            # on an error, drop what was not started; finished batches are not needed
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None

    def submit(self, images: list[Encoded], height: int, width: int) -> Future | _Done:
        """A handle whose `result()` is `decode_batch(images, height, width)`."""
        while self._queued and self._queued[0].done():
            self._queued.popleft()
        if not self._ready.is_set() or len(self._queued) >= 2 * self.workers:
            return _Done(decode_batch(images, height, width))
        assert self._executor is not None
        future = self._executor.submit(decode_batch, images, height, width)
        self._queued.append(future)
        return future


def _context() -> multiprocessing.context.BaseContext:
    """A fork server where there is one (Linux, macOS): no fork of a process that runs threads
    (zarr's event loop, the store's writer), and the server imports numpy, Pillow and the main
    module once, so that a worker starts in milliseconds. Spawn elsewhere. Either way workers
    import the main module, which must guard its work with `if __name__ == "__main__":`, as
    multiprocessing asks (the `sefa` command does)."""
    if "forkserver" in multiprocessing.get_all_start_methods():
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(["__main__", __name__])
        return ctx
    return multiprocessing.get_context("spawn")
