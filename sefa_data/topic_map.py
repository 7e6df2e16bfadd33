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

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from sefa_data.config_io import from_dict, load_yaml
from sefa_data.errors import ConfigError

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

    def validate(self) -> None:
        if not self.topic.startswith("/"):
            raise ConfigError(f"topic '{self.topic}' must start with '/'", key="topic")
        if self.frames is not None and len(self.frames) != 2:
            raise ConfigError("frames must be [parent, child]", key="frames")
        if self.image_size is not None:
            if len(self.image_size) != 2 or min(self.image_size) <= 0:
                raise ConfigError("image_size must be [height, width] with positive sizes",
                                  key="image_size")
            if self.resample == "linear":
                raise ConfigError("linear resampling is for low-dimensional values, not images",
                                  key="resample")
        if self.tolerance_s is not None and self.tolerance_s <= 0:
            raise ConfigError("tolerance_s must be positive", key="tolerance_s")

    @property
    def is_image(self) -> bool:
        return self.image_size is not None


@dataclass
class SplitSpec:
    gap_s: float | None = None
    marker_topic: str | None = None


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
        if self.fps <= 0:
            raise ConfigError("fps must be positive", key="fps")
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
