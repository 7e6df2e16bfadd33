"""How fast data goes into an episode store and comes back out as training windows.

Two measurements on the real recordings of ../shared/data (see its MANIFEST.md). Both are meant
to be read as ratios on one machine: absolute rates vary several-fold between a laptop and a
small CI VM, while the ratios say where our own code costs time.

Ingest (`ingest_throughput`). For each recording, (a) the reader library alone reading and
decoding every message or frame (rosbags AnyReader + deserialize for the KUKA bags; a plain zarr
read of every array for Push-T) against (b) our whole `ingest` into a fresh store (hashing,
selection, resampling, validation, compression and writing included), in messages/s. The ratio
ours/raw is how close ingest comes to the floor the reader sets; the goal (issue 2) is at least
0.6. The store is written twice: to RAM (/dev/shm when there is one), which compares our code
with the reader on equal terms (the source is read from the page cache), and to disk, which adds
the file system's cost of one file per image frame (Push-T: 25,650 files; on a small VM that
alone varies from 2 to 12 s between runs). Times are medians over `repeat` runs.

Sampling (`sampler_throughput`). Training windows/s from a Push-T store, `batch()` against
`window()` one by one, which is what a data loader gains from asking for a whole batch at once.
Windows follow Diffusion Policy's Push-T config (horizon 16, 2 observation steps, 8 action
steps). Indices are drawn uniformly at random, as a shuffled loader would, so image reads mostly
miss the frame cache (4,096 of 25,650 frames).
"""

from __future__ import annotations

import contextlib
import os
import platform
import shutil
import statistics
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np

from sefa_data.errors import SefaInputError
from sefa_data.ingest import IngestOptions, ingest

# Where a clone of this repository finds the shared recordings (as tests/conftest.py does).
DEFAULT_DATA_DIR = Path(__file__).resolve().parents[3] / "shared" / "data"
RATIO_GOAL = 0.6

Log = Callable[[str], None]


def _quiet(_: str) -> None:
    pass


# ---- the machine

def machine_description() -> dict:
    """What the numbers were measured on: rates only compare within one machine."""
    cpu = None
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:  # not Linux
        pass
    try:
        import torch

        # torch's thread count sets the speed of to_torch and of everything after sampling
        torch_version, torch_threads = torch.__version__, torch.get_num_threads()
    except ImportError:
        torch_version, torch_threads = None, None
    return {"cpu": cpu or platform.processor() or platform.machine(), "cores": os.cpu_count(),
            "torch": torch_version, "torch_threads": torch_threads,
            "platform": platform.platform(), "python": platform.python_version()}


def machine_summary(machine: dict) -> str:
    """One line for a report's heading."""
    text = f"{machine['cpu']}, {machine['cores']} cores, Python {machine['python']}"
    if machine.get("torch"):
        text += f", torch {machine['torch']} ({machine['torch_threads']} threads)"
    return text


def ram_dir() -> Path | None:
    """A RAM-backed folder for scratch stores, or None (the system temp dir) without one."""
    shm = Path("/dev/shm")
    return shm if shm.is_dir() and os.access(shm, os.W_OK) else None


def _require_dir(path: Path) -> Path:
    path = Path(path)
    if not path.is_dir():
        raise SefaInputError("no recordings here (the real recordings of ../shared/data are "
                             "not part of a clone; give their folder with --data)", file=str(path))
    return path


def _require(path: Path) -> Path:
    if not path.exists():
        raise SefaInputError("recording not found", file=str(path))
    return path


def timed(fn: Callable[[], object], repeat: int, before: Callable[[], object] = lambda: None
          ) -> tuple[float, object]:
    """Median wall time of `fn` over `repeat` runs; `before` runs untimed ahead of each."""
    times, result = [], None
    for _ in range(repeat):
        before()
        t = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), result


# ---- ingest

JOINTS = ", ".join(f"lwr_arm_{i}_joint" for i in range(7))
KUKA_MAP = f"""
fps: 100
features:
  observation.joint_pos: {{topic: /joint_states, field: "position[{JOINTS}]"}}
  observation.joint_vel: {{topic: /joint_states, field: "velocity[{JOINTS}]"}}
  action: {{topic: /joint_states, field: "effort[{JOINTS}]"}}
"""


def raw_rosbags(path: Path) -> int:
    """Messages read and deserialized by rosbags alone: the floor for a bag or MCAP ingest."""
    from rosbags.highlevel import AnyReader

    n = 0
    with AnyReader([path]) as reader:
        for conn, _, raw in reader.messages():
            reader.deserialize(raw, conn.msgtype)
            n += 1
    return n


def raw_zarr(path: Path) -> int:
    """Frames of a Zarr replay buffer read by zarr alone: the floor for a Zarr import."""
    import zarr

    root = zarr.open_group(str(path), mode="r")
    frames = 0
    for key in root["data"].array_keys():
        frames = len(root["data"][key][:])
    return frames


def _kuka_options(scratch: Path) -> IngestOptions:
    topic_map = scratch / "kuka.yaml"
    topic_map.write_text(KUKA_MAP)
    return IngestOptions(topic_map=str(topic_map))


@dataclass(frozen=True)
class Recording:
    name: str  # what `only` selects by
    label: str
    file: str  # in the data folder
    read_raw: Callable[[Path], int]
    options: Callable[[Path], IngestOptions]  # given a scratch folder for a topic map


RECORDINGS = (
    Recording("kuka_ros1", "KUKA ROS1 bag (4101 msgs)", "kuka_lwr_honeypot_joint_states.bag",
              raw_rosbags, _kuka_options),
    Recording("kuka_mcap", "KUKA ROS2 MCAP (4101 msgs)", "kuka_lwr_honeypot_ros2_mcap",
              raw_rosbags, _kuka_options),
    Recording("pusht", "Push-T zarr (25650 frames, images)", "pusht_cchi_v7_replay.zarr",
              raw_zarr, lambda _: IngestOptions(fps=10)),
)
RECORDING_NAMES = tuple(r.name for r in RECORDINGS)


def _select(only: Sequence[str] | None) -> list[Recording]:
    if not only:
        return list(RECORDINGS)
    unknown = [n for n in only if n not in RECORDING_NAMES]
    if unknown:
        raise SefaInputError(f"unknown recording '{unknown[0]}' (available: "
                             f"{', '.join(RECORDING_NAMES)})", key="only")
    return [r for r in RECORDINGS if r.name in only]


def ingest_throughput(data_dir: Path = DEFAULT_DATA_DIR, *, repeat: int = 3,
                      disk_dir: Path | None = None, only: Sequence[str] | None = None,
                      log: Log = _quiet) -> dict:
    """Raw reader rate against our ingest rate, to RAM and to disk, per recording.

    Returns {"repeat", "ram_dir", "disk_dir", "rows", "lowest_ratio", "goal"}; each row has
    name, input (a label), path, messages, raw_s, raw_msgs_per_s and, for where in ram and
    disk, ours_{where}_s, ours_{where}_msgs_per_s and ratio_{where} (ours / raw rate).
    `only` picks recordings by name (RECORDING_NAMES); `disk_dir` defaults to the temp dir.
    """
    recordings = _select(only)
    if repeat < 1:
        raise SefaInputError(f"repeat must be at least 1, got {repeat}", key="repeat")
    data_dir = _require_dir(data_dir)
    paths = [_require(data_dir / r.file) for r in recordings]
    rows = []
    with tempfile.TemporaryDirectory(dir=ram_dir()) as ram, \
            tempfile.TemporaryDirectory(dir=disk_dir) as disk:
        for rec, path in zip(recordings, paths):
            log(f"ingest: {rec.label}")
            options = rec.options(Path(ram))
            rec.read_raw(path)  # warm the page cache and the imports once, for both sides
            t_raw, n = timed(partial(rec.read_raw, path), repeat)
            row = {"name": rec.name, "input": rec.label, "path": str(path), "messages": n,
                   "raw_s": t_raw, "raw_msgs_per_s": n / t_raw}
            for where, base in (("ram", Path(ram)), ("disk", Path(disk))):
                out = base / "bench.zarr"
                t, _ = timed(partial(ingest, [path], out, options), repeat,
                             before=partial(shutil.rmtree, out, ignore_errors=True))
                # t_raw / t is the same number as (n / t) / (n / t_raw): our rate over the raw rate
                row.update({f"ours_{where}_s": t, f"ours_{where}_msgs_per_s": n / t,
                            f"ratio_{where}": t_raw / t})
            rows.append(row)
    return {"repeat": repeat, "ram_dir": str(ram_dir() or tempfile.gettempdir()),
            "disk_dir": str(disk_dir or tempfile.gettempdir()), "rows": rows,
            "lowest_ratio": {w: float(np.min([r[f"ratio_{w}"] for r in rows]))
                             for w in ("ram", "disk")},
            "goal": RATIO_GOAL}


# ---- image ingest (issue 14)

IMAGE_SIZES = ((96, 96), (84, 84))  # Push-T's own size, and a resize (the path a camera takes)


def decode_images(path: Path, topic: str, size: tuple[int, int]) -> int:
    """Image messages of `topic` read by rosbags and decoded to RGB uint8 arrays by sefa's own
    decoder, one by one, nothing else: the floor for an image ingest. `size` is the images' own
    size, so that nothing is resized."""
    from rosbags.highlevel import AnyReader

    from sefa_data.readers.image_decode import decode, encoded

    n = 0
    with AnyReader([path]) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        for conn, _, raw in reader.messages(connections=conns):
            decode(encoded(reader.deserialize(raw, conn.msgtype), conn.msgtype), *size)
            n += 1
    return n


IMAGE_RECORDINGS = ("mcap/compressed", "mcap/raw", "ros1/compressed", "ros1/raw")


def _recordings(frames, folder: Path, names: Sequence[str], jpeg_quality: int, log: Log
                ) -> dict[tuple, Path]:
    """The Push-T recordings `names` (IMAGE_RECORDINGS: container/message) in `folder`, written
    once and reused while the folder's name (frames, JPEG quality) matches. Each is written in
    folder/.partial and then moved into place, so that a killed run leaves no half recording
    behind."""
    from sefa_data.bench.pusht_bags import recording_name, write_recording

    out = {}
    partial_dir = folder / ".partial"
    for name in names:
        container, message = name.split("/")
        path = folder / recording_name(container, message)
        if not path.exists():
            log(f"writing {path}")
            shutil.rmtree(partial_dir, ignore_errors=True)
            partial_dir.mkdir()
            write_recording(partial_dir / path.name, frames, container, message, jpeg_quality)
            (partial_dir / path.name).rename(path)
            partial_dir.rmdir()
        out[container, message] = path
    return out


def _size(path: Path) -> int:
    return path.stat().st_size if path.is_file() else sum(f.stat().st_size for f in path.iterdir())


def _pixel_error(store_path: Path, frames, size: tuple[int, int]) -> dict:
    """Stored frames against the source frames brought to `size` by the same bilinear resize:
    0 for raw images, the JPEG error for compressed ones. Low-dim keys must match exactly."""
    from sefa_data.readers.image_decode import Encoded, decode
    from sefa_data.store.zarr_store import EpisodeStore

    store = EpisodeStore.open(store_path)
    data = store.root["data"]
    h, w, _ = frames.img.shape[1:]
    ref = np.stack([decode(Encoded(f.reshape(-1), encoding="rgb8", height=h, width=w,
                                   step=w * 3), *size) for f in frames.img])
    img = data["img"][:]
    if img.shape != ref.shape or not np.array_equal(store.episode_ends, frames.episode_ends):
        raise SefaInputError(f"the store holds {img.shape} frames in {store.n_episodes} episodes "
                             f"where the source has {ref.shape} in {len(frames.episode_ends)}",
                             file=str(store_path))
    for key in ("state", "action"):
        if not np.array_equal(data[key][:], getattr(frames, key)):
            raise SefaInputError("stored values differ from the source", file=str(store_path),
                                 key=key)
    diff = np.abs(img.astype(np.int16) - ref)
    return {"max": int(diff.max()), "mean": float(diff.mean())}


def image_ingest_throughput(data_dir: Path = DEFAULT_DATA_DIR, *, frames: int = 5000,
                            repeat: int = 3, sizes: Sequence[tuple[int, int]] = IMAGE_SIZES,
                            jpeg_quality: int = 90, decode_workers: int | None = None,
                            only: Sequence[str] | None = None, work_dir: Path | None = None,
                            log: Log = _quiet) -> dict:
    """Frames/s of decoding alone against our whole `ingest`, on camera recordings made from
    the first Push-T episodes (`sefa_data.bench.pusht_bags`: rosbags' own writers, MCAP and ROS 1,
    CompressedImage as JPEG and raw rgb8 Image).

    Decoding alone (`decode_images`) is rosbags reading every image message and sefa's decoder
    turning it into an RGB uint8 array at its own size, one by one. Ingest is `ingest` of the
    recording into a fresh store in RAM (hashing, the low-dim topics, decoding, resizing,
    alignment, validation, compression and writing), one row per image size, twice: with the
    reader decoding every image, and with `decode_workers` processes decoding beside it
    (default `image_decode.default_workers()`; 0, or fewer frames than a pool is started for,
    leaves that measurement out). A ratio is an
    ingest rate over the decoding rate; the goal of issue 14 is at least 0.6. After the timing,
    each row's store is checked against the source frames (`pixel_error`: 0 for raw images),
    and the workers' store must hold the same frames as the reader's.

    `only` picks recordings by name (IMAGE_RECORDINGS, e.g. "ros1/compressed"; default all).
    Recordings go to `work_dir/pusht_bags_<frames>f_q<quality>` and are reused by later runs;
    without `work_dir`, to a temporary folder (in RAM when there is one) removed at the end.
    Returns {"frames", "episodes", "repeat", "jpeg_quality", "decode_workers", "recordings"
    (name: bytes), "rows", "lowest_ratio" {reader, workers}, "goal"}; rows have container,
    message, input, path, image_size, frames, decode_s, decode_fps, and for how in reader and
    workers {how}_s, {how}_fps and {how}_ratio (None without workers), and pixel_error
    {max, mean}.
    """
    from sefa_data.readers.image_decode import MIN_IMAGES_FOR_POOL, default_workers
    from sefa_data.bench.pusht_bags import IMAGE_TOPIC, pusht_frames, topic_map_text

    if repeat < 1:
        raise SefaInputError(f"repeat must be at least 1, got {repeat}", key="repeat")
    unknown = [name for name in only or () if name not in IMAGE_RECORDINGS]
    if unknown:
        raise SefaInputError(f"unknown recording '{unknown[0]}' (available: "
                             f"{', '.join(IMAGE_RECORDINGS)})", key="only")
    names = [name for name in IMAGE_RECORDINGS if not only or name in only]
    workers = default_workers() if decode_workers is None else decode_workers
    source = pusht_frames(_require_dir(data_dir), frames)
    log(f"{len(source)} Push-T frames ({len(source.episode_ends)} episodes)")
    if len(source) < MIN_IMAGES_FOR_POOL:  # the reader would decode them all anyway
        log(f"fewer than {MIN_IMAGES_FOR_POOL} frames: no decode workers")
        workers = 0
    with contextlib.ExitStack() as stack:
        if work_dir is None:
            folder = Path(stack.enter_context(tempfile.TemporaryDirectory(dir=ram_dir())))
        else:
            folder = Path(work_dir) / f"pusht_bags_{len(source)}f_q{jpeg_quality}"
            folder.mkdir(parents=True, exist_ok=True)
        recordings = _recordings(source, folder, names, jpeg_quality, log)
        scratch = Path(stack.enter_context(tempfile.TemporaryDirectory(dir=ram_dir())))
        rows = []
        for (container, message), path in recordings.items():
            label = f"{'MCAP (ROS 2)' if container == 'mcap' else 'ROS 1 bag'} {message}"
            log(f"image ingest: {label}")
            read = partial(decode_images, path, IMAGE_TOPIC[message], source.img.shape[1:3])
            n = read()  # warm the page cache and the imports once, for both sides
            if n != len(source):
                raise SefaInputError(f"{n} image messages where {len(source)} were written",
                                     file=str(path))
            t_decode, _ = timed(read, repeat)
            for size in sizes:
                topic_map = scratch / f"{message}_{size[0]}x{size[1]}.yaml"
                topic_map.write_text(topic_map_text(message, size))
                row = {"container": container, "message": message, "input": label,
                       "path": str(path), "image_size": list(size), "frames": n,
                       "decode_s": t_decode, "decode_fps": n / t_decode}
                rows.append(_ingest_row(row, path, topic_map, source, size, workers, repeat,
                                        scratch))
        sizes_of = {p.name: _size(p) for p in recordings.values()}
    lowest = {how: min((r[f"{how}_ratio"] for r in rows if r[f"{how}_ratio"] is not None),
                       default=None) for how in ("reader", "workers")}
    return {"frames": len(source), "episodes": len(source.episode_ends), "repeat": repeat,
            "jpeg_quality": jpeg_quality, "decode_workers": workers, "recordings": sizes_of,
            "rows": rows, "lowest_ratio": lowest, "goal": RATIO_GOAL}


def _ingest_row(row: dict, path: Path, topic_map: Path, source, size: tuple[int, int],
                workers: int, repeat: int, scratch: Path) -> dict:
    """`row` with the ingest times of one recording at one image size, by the reader alone and
    with decode workers, and the stored frames checked against the source."""
    n, t_decode = row["frames"], row["decode_s"]
    stores = {}
    for how, w in (("reader", 0), ("workers", workers)):
        row.update({f"{how}_s": None, f"{how}_fps": None, f"{how}_ratio": None})
        if how == "workers" and w == 0:
            continue
        out = stores[how] = scratch / f"{how}.zarr"
        options = IngestOptions(topic_map=str(topic_map), decode_workers=w)
        t, _ = timed(partial(ingest, [path], out, options), repeat,
                     before=partial(shutil.rmtree, out, ignore_errors=True))
        # t_decode / t is (n / t) / (n / t_decode): the ingest rate over decoding's
        row.update({f"{how}_s": t, f"{how}_fps": n / t, f"{how}_ratio": t_decode / t})
    row["pixel_error"] = _pixel_error(stores["reader"], source, size)
    if "workers" in stores:
        _same_frames(stores["reader"], stores["workers"])
    for out in stores.values():
        shutil.rmtree(out, ignore_errors=True)
    return row


def _same_frames(a: Path, b: Path) -> None:
    import zarr

    if not np.array_equal(zarr.open_group(str(a), mode="r")["data/img"][:],
                          zarr.open_group(str(b), mode="r")["data/img"][:]):
        raise SefaInputError(f"images decoded in worker processes differ from the reader's "
                             f"({a})", file=str(b), key="img")


# ---- sampling

PUSHT_FILE = "pusht_cchi_v7_replay.zarr"
WINDOW = {"horizon": 16, "n_obs_steps": 2, "n_action_steps": 8}  # Diffusion Policy's Push-T
LOWDIM = ["keypoint", "state"]
IMAGE = "img"


def rate(step: Callable[[], int], seconds: float) -> float:
    """Windows per second of `step` (which returns how many windows it produced)."""
    step()  # warm-up: first-touch allocations, imports
    n, start = 0, time.perf_counter()
    while (elapsed := time.perf_counter() - start) < seconds:
        n += step()
    return n / elapsed


def batch_step(s, size: int, rng: np.random.Generator, torch_too: bool = False):
    from sefa_data.sampler import to_torch

    def step() -> int:
        b = s.batch(rng.integers(0, len(s), size))
        if torch_too:
            to_torch(b, "cpu", s.image_keys)
        return size
    return step


def window_step(s, size: int, rng: np.random.Generator):
    def step() -> int:
        for i in rng.integers(0, len(s), size):
            s.window(int(i))
        return size
    return step


def sampler_throughput(store: Path | None = None, *, data_dir: Path = DEFAULT_DATA_DIR,
                       batch: int = 256, seconds: float = 3.0, log: Log = _quiet) -> dict:
    """Windows/s of `batch()` against `window()` one by one, on a Push-T store.

    With no `store`, Push-T from `data_dir` is ingested into a temporary folder (in RAM when
    there is one) and removed afterwards. A store without the `img` key (a low-dim ingest, for
    a quick run) gets the low-dim measurements only. Returns {"store", "ingest_s", "windows",
    "batch", "seconds", "rows" (case, label, windows_per_s), "batch_over_window" (low_dim,
    images), "image_cache" (frames, hits, misses, hit_rate)}; the image entries are None
    without images.
    """
    if batch < 1 or seconds <= 0:
        raise SefaInputError(f"need batch >= 1 and seconds > 0, got {batch} and {seconds}")
    tmp, ingest_s = None, None
    try:
        if store is None:
            source = _require(_require_dir(data_dir) / PUSHT_FILE)
            tmp = Path(tempfile.mkdtemp(dir=ram_dir()))
            store = tmp / "pusht.zarr"
            t = time.perf_counter()
            ingest([source], store, IngestOptions(fps=10))
            ingest_s = time.perf_counter() - t
            log(f"ingested {source.name} into {store} in {ingest_s:.1f} s")
        result = _measure_sampler(Path(store), batch, seconds, log)
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    return {"store": None if tmp else str(store), "ingest_s": ingest_s, **result}


def _measure_sampler(path: Path, size: int, seconds: float, log: Log) -> dict:
    # torch comes with the sampler and takes seconds to import; the ingest measurement skips it
    from sefa_data.sampler import SequenceSampler
    from sefa_data.store.zarr_store import EpisodeStore

    store = EpisodeStore.open(path)
    rng = np.random.default_rng(0)  # one generator for all cases, in order, as before
    low = SequenceSampler(store, **WINDOW, obs_keys=LOWDIM)
    cases = [
        ("low_dim_batch", "low-dim  (keypoint, state, action)  batch()", batch_step(low, size, rng)),
        ("low_dim_window", "low-dim  (keypoint, state, action)  window()", window_step(low, size, rng)),
    ]
    img = None
    if store.attrs["features"].get(IMAGE, {}).get("type") == "image":
        img = SequenceSampler(store, **WINDOW, obs_keys=[IMAGE, *LOWDIM])
        through_zarr = SequenceSampler(store, **WINDOW, obs_keys=[IMAGE, *LOWDIM])
        # no direct chunk-file reads: the generic zarr read, to show what they save
        through_zarr._images[IMAGE]._chunk_file = None
        cases += [
            ("images_batch", "images   (img + low-dim)            batch()", batch_step(img, size, rng)),
            ("images_batch_to_torch", "images   (img + low-dim)  batch() + to_torch",
             batch_step(img, size, rng, True)),
            ("images_window", "images   (img + low-dim)            window()", window_step(img, size, rng)),
            ("images_zarr_batch", "images, read through zarr           batch()",
             batch_step(through_zarr, size, rng)),
        ]
    log(f"{len(low)} training windows, horizon 16, n_obs_steps 2, n_action_steps 8, batch {size}")
    rows = []
    for case, label, step in cases:
        rows.append({"case": case, "label": label, "windows_per_s": rate(step, seconds)})
    r = {row["case"]: row["windows_per_s"] for row in rows}
    cache = img._images[IMAGE] if img is not None else None
    return {
        "windows": len(low), **WINDOW, "batch": size, "seconds": seconds, "rows": rows,
        "batch_over_window": {
            "low_dim": r["low_dim_batch"] / r["low_dim_window"],
            "images": r["images_batch"] / r["images_window"] if img is not None else None},
        "image_cache": None if cache is None else {
            "frames": len(cache), "hits": cache.hits, "misses": cache.misses,
            "hit_rate": cache.hits / max(1, cache.hits + cache.misses)},
    }
