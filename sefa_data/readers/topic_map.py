"""The topic map: which topic and field of a recording becomes which dataset key.

YAML form (a `sefa ingest --scaffold` writes a starter one from a bag's topics)::

    fps: 50
    stamp: auto                   # auto | header | log (auto: header when the message has one)
    max_stamp_skew_s: 60.0        # header vs log time; null turns the check off
    features:
      observation.state:
        topic: /joint_states
        field: position[lwr_arm_0_joint, lwr_arm_1_joint]
      observation.velocity:
        topic: /joint_states
        field: velocity[lwr_arm_0_joint, lwr_arm_1_joint]
        resample: linear
      observation.base_pose:
        topic: /tf
        frames: [odom, base_link]   # tf2 lookup: pose of base_link in odom, x y z qx qy qz qw
      observation.images.front:
        topic: /camera/image_raw/compressed
        image_size: [96, 96]
    split:
      gap_s: 2.0                  # a new episode after a silence longer than this
      marker_topic: /episode_start
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from sefa_data.config_io import from_dict, load_yaml
from sefa_data.errors import ConfigError, SefaInputError
from sefa_data.validate import MAX_IMAGE_SIDE, check_fps, check_key, numeric_dtype

StampSource = Literal["auto", "header", "log"]
Resample = Literal["hold", "nearest", "linear"]


@dataclass
class FeatureSpec:
    topic: str
    # Selector inside the message: a dotted path (`pose.pose.position`), a joint-name pick
    # (`position[lwr_arm_0_joint, lwr_arm_1_joint]`), or empty for the whole message. Nested
    # messages flatten to their numeric fields in definition order (a Pose is x y z qx qy qz qw).
    field: str = ""
    frames: list[str] | None = None  # [parent, child] for a tf2_msgs/TFMessage topic
    image_size: list[int] | None = None  # [height, width]; marks the feature as an image
    stamp: StampSource | None = None  # None: the map's `stamp`
    resample: Resample = "hold"
    tolerance_s: float | None = None  # `nearest`: the largest allowed distance to a sample
    optional: bool = False  # an optional key may be absent; it never trims the episode
    dtype: str | None = None  # numpy dtype of the stored array; float32 for low-dim by default
    # a `dtype` that changes values (float joint angles to uint8, an int out of range) is an
    # error unless this says it is meant
    allow_lossy_cast: bool = False

    def validate(self) -> None:
        # relative names (no leading '/') are matched as ROS records them; MCAP channels of
        # other encodings may use any text, so only empty names and blanks are refused
        if not _TOPIC.fullmatch(self.topic):
            raise ConfigError(f"topic {self.topic!r} is empty or contains spaces or control "
                              "characters", key="topic")
        if self.frames is not None and (len(self.frames) != 2 or not all(f.strip() for f in self.frames)):
            raise ConfigError("frames must be [parent, child]", key="frames")
        if self.image_size is not None:
            if len(self.image_size) != 2 or min(self.image_size) <= 0 \
                    or max(self.image_size) > MAX_IMAGE_SIDE:
                raise ConfigError(f"image_size must be [height, width] with sizes from 1 to "
                                  f"{MAX_IMAGE_SIDE}, got {self.image_size}", key="image_size")
            if self.resample == "linear":
                raise ConfigError("linear resampling is for low-dimensional values, not images",
                                  key="resample")
        _positive(self.tolerance_s, "tolerance_s")
        if self.dtype is not None and numeric_dtype(self.dtype) is None:
            raise ConfigError(f"unknown or non-numeric dtype {self.dtype!r} (use e.g. float32, "
                              "float64, int32, uint8, bool)", key="dtype")

    @property
    def is_image(self) -> bool:
        return self.image_size is not None


@dataclass
class SplitSpec:
    gap_s: float | None = None
    marker_topic: str | None = None

    def validate(self) -> None:
        _positive(self.gap_s, "gap_s")
        if self.marker_topic is not None and not _TOPIC.fullmatch(self.marker_topic):
            raise ConfigError(f"marker_topic {self.marker_topic!r} is empty or contains spaces "
                              "or control characters", key="marker_topic")


_TOPIC = re.compile(r"[^\s\x00-\x1f\x7f]+")


def _positive(value: float | None, key: str) -> None:
    if value is not None and not (math.isfinite(value) and value > 0):
        raise ConfigError(f"must be a positive number of seconds, got {value!r}", key=key)


@dataclass
class TopicMap:
    fps: float
    features: dict[str, FeatureSpec]
    stamp: StampSource = "auto"
    max_stamp_skew_s: float | None = 60.0
    tolerance_s: float | None = None  # default for `nearest` features: one frame period
    split: SplitSpec = field(default_factory=SplitSpec)
    min_length: int = 2  # shorter episodes (after trimming and splitting) are an error

    def validate(self) -> None:
        try:
            check_fps(self.fps)
        except SefaInputError as e:
            raise ConfigError(e.what, key="fps") from None
        for key in self.features:
            check_key(key, error=ConfigError)
        _positive(self.tolerance_s, "tolerance_s")
        if self.max_stamp_skew_s is not None and not (math.isfinite(self.max_stamp_skew_s)
                                                      and self.max_stamp_skew_s >= 0):
            raise ConfigError("must be a number of seconds >= 0, or null to turn the check "
                              f"off; got {self.max_stamp_skew_s!r}", key="max_stamp_skew_s")
        if self.min_length < 1:
            raise ConfigError(f"must be at least 1 frame, got {self.min_length}",
                              key="min_length")
        if not self.features:
            raise ConfigError("features is empty: map at least one dataset key to a topic",
                              key="features")
        if all(f.optional for f in self.features.values()):
            raise ConfigError("every feature is optional: at least one must be required",
                              key="features")

    def stamp_of(self, spec: FeatureSpec) -> StampSource:
        return spec.stamp or self.stamp

    def tolerance_of(self, spec: FeatureSpec) -> float:
        return spec.tolerance_s or self.tolerance_s or 1.0 / self.fps


def load_topic_map(path: str | Path, overrides: dict | None = None) -> TopicMap:
    data = load_yaml(path)
    if overrides:
        data = {**data, **overrides}
    return from_dict(TopicMap, data, source=str(path))
