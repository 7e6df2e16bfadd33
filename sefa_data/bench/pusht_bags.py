"""Real Push-T frames as camera recordings: a ROS 2 MCAP bag and a ROS 1 bag with images.

No public recording of a real arm with camera images was found (../shared/data/MANIFEST.md,
"Gaps"), so the image ingest benchmark transcodes the Push-T frames (96 x 96 RGB, 10 Hz) into
recordings written by rosbags' own writers: `rosbag2.Writer` with MCAP storage and
`rosbag1.Writer`. Each recording carries one image topic, either `sensor_msgs/CompressedImage`
(JPEG, quality 90 by default, as camera drivers commonly publish) or raw `sensor_msgs/Image`
(rgb8), plus the agent state and action as `std_msgs/Float32MultiArray`, so that it ingests
into a normal store with `TOPIC_MAP`.

Episodes follow one another with a one-second silence, which the map's `split.gap_s` turns back
into the Push-T episodes; every message of frame k carries the same stamp, so the ingested store
holds the source frames one for one.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from sefa_data.errors import SefaInputError

PUSHT_FILE = "pusht_cchi_v7_replay.zarr"
Container = Literal["mcap", "ros1"]
Message = Literal["compressed", "raw"]
CONTAINERS: tuple[Container, ...] = ("mcap", "ros1")
MESSAGES: tuple[Message, ...] = ("compressed", "raw")
IMAGE_TOPIC = {"compressed": "/camera/image/compressed", "raw": "/camera/image_raw"}
IMAGE_TYPE = {"compressed": "sensor_msgs/msg/CompressedImage", "raw": "sensor_msgs/msg/Image"}
ARRAY_TYPE = "std_msgs/msg/Float32MultiArray"
FPS = 10
PERIOD_NS = 1_000_000_000 // FPS
EPISODE_GAP_NS = 1_000_000_000  # silence between episodes; split at half of it
T0_NS = 1_700_000_000 * 1_000_000_000  # a plausible wall-clock start

TOPIC_MAP = """\
fps: {fps}
features:
  img: {{topic: {topic}, image_size: [{height}, {width}]}}
  state: {{topic: /state, field: data}}
  action: {{topic: /action, field: data}}
split: {{gap_s: {gap_s}}}
"""


@dataclass(frozen=True)
class PushtFrames:
    """The first whole Push-T episodes: images as uint8, the rest as stored."""

    img: np.ndarray  # (N, 96, 96, 3) uint8
    state: np.ndarray  # (N, 5) float32
    action: np.ndarray  # (N, 2) float32
    episode_ends: np.ndarray  # (E,) int64, exclusive

    def __len__(self) -> int:
        return len(self.img)


def pusht_frames(data_dir: Path, frames: int) -> PushtFrames:
    """Whole episodes from the start of Push-T, as few as give at least `frames` frames."""
    import zarr

    path = Path(data_dir) / PUSHT_FILE
    if not path.is_dir():
        raise SefaInputError("Push-T not found (the real recordings of ../shared/data are not "
                             "part of a clone; give their folder with --data)", file=str(path))
    if frames < 1:
        raise SefaInputError(f"frames must be at least 1, got {frames}", key="frames")
    root = zarr.open_group(str(path), mode="r")
    all_ends = root["meta/episode_ends"][:].astype(np.int64)
    n_episodes = min(int(np.searchsorted(all_ends, frames)) + 1, len(all_ends))
    ends = all_ends[:n_episodes]
    n = int(ends[-1])
    img = root["data/img"][:n]
    # Push-T stores its images as float32 holding whole numbers 0..255; a camera sends uint8
    if not (np.array_equal(img, np.round(img)) and img.min() >= 0 and img.max() <= 255):
        raise SefaInputError("images are not whole numbers in 0..255", file=str(path),
                             key="data/img")
    return PushtFrames(img.astype(np.uint8), root["data/state"][:n].astype(np.float32),
                       root["data/action"][:n].astype(np.float32), ends)


def frame_times_ns(frames: PushtFrames) -> np.ndarray:
    """Stamp of every frame: 10 Hz within an episode, a one-second silence between episodes."""
    episode = np.searchsorted(frames.episode_ends, np.arange(len(frames)), side="right")
    return T0_NS + np.arange(len(frames), dtype=np.int64) * PERIOD_NS + episode * EPISODE_GAP_NS


def encode_jpeg(rgb: np.ndarray, quality: int) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="JPEG", quality=quality)
    return buf.getvalue()


def write_recording(path: Path, frames: PushtFrames, container: Container, message: Message,
                    jpeg_quality: int = 90) -> Path:
    """Write `frames` as a recording at `path` (a .bag file for ros1, a bag directory for mcap).

    Per frame, in this order and with one stamp: the image, /state, /action."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin, Writer as Writer2
    from rosbags.typesys import Stores, get_typestore

    if container not in CONTAINERS or message not in MESSAGES:
        raise ValueError(f"unknown recording kind {container}/{message}")
    ros1 = container == "ros1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    serialize = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    T = ts.types
    topics = {IMAGE_TOPIC[message]: IMAGE_TYPE[message], "/state": ARRAY_TYPE,
              "/action": ARRAY_TYPE}
    layout = T["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0)
    h, w, _ = frames.img.shape[1:]

    def header(ns: int):
        stamp = T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
        if ros1:
            return T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id="camera")
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id="camera")

    def image(i: int, ns: int):
        if message == "compressed":
            data = np.frombuffer(encode_jpeg(frames.img[i], jpeg_quality), np.uint8)
            return T[IMAGE_TYPE[message]](header=header(ns), format="jpeg", data=data)
        return T[IMAGE_TYPE[message]](header=header(ns), height=h, width=w, encoding="rgb8",
                                      is_bigendian=0, step=w * 3,
                                      data=frames.img[i].reshape(-1))

    writer = Writer1(path) if ros1 else Writer2(path, version=9,
                                                storage_plugin=StoragePlugin.MCAP)
    with writer as wr:
        conns = {t: wr.add_connection(t, typ, typestore=ts) for t, typ in topics.items()}
        for i, ns in enumerate(frame_times_ns(frames).tolist()):
            msgs = {IMAGE_TOPIC[message]: image(i, ns),
                    "/state": T[ARRAY_TYPE](layout=layout, data=frames.state[i]),
                    "/action": T[ARRAY_TYPE](layout=layout, data=frames.action[i])}
            for topic, msg in msgs.items():
                wr.write(conns[topic], ns, serialize(msg, topics[topic]))
    return path


def recording_name(container: Container, message: Message) -> str:
    return f"pusht_{message}.bag" if container == "ros1" else f"pusht_{message}_mcap"


def topic_map_text(message: Message, size: tuple[int, int]) -> str:
    return TOPIC_MAP.format(fps=FPS, topic=IMAGE_TOPIC[message], height=size[0], width=size[1],
                            gap_s=EPISODE_GAP_NS / 2e9)
