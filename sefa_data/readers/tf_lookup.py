"""TF lookups: the pose of one frame in another, as a sample stream, from recorded tf2 messages.

The reader feeds every `tf2_msgs/TFMessage` of a TF topic (and of `/tf_static`) into a
`TfCollector` in recorded order. `tf_stream` then finds the chain of edges between the two
frames of a feature (walking up to their common ancestor, inverting the edges on the way up)
and composes the chain at every message that updates one of its dynamic edges, holding the
other edges at their latest value. Static edges hold for all time, so a latched `/tf_static`
message recorded once, before or after the first `/tf`, is enough.

Poses are arrays ``[x, y, z, qx, qy, qz, qw]`` (the ROS quaternion order); the maths is plain
vectorised numpy over a leading sample axis.
"""

from __future__ import annotations

from array import array
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sefa_data.episode import Stream
from sefa_data.errors import SefaInputError

POSE_NAMES = ["x", "y", "z", "qx", "qy", "qz", "qw"]
STATIC_TOPIC = "/tf_static"

# --- quaternion and pose maths (xyzw, any leading shape) -----------------------------------------


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a*b: rotating by b, then by a."""
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz], axis=-1)


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    return q * np.array([-1.0, -1.0, -1.0, 1.0])


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors v by unit quaternions q (q v q*, in the expanded form)."""
    u, w = q[..., :3], q[..., 3:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """T_ac = T_ab * T_bc for poses a = T_ab and b = T_bc."""
    xyz = a[..., :3] + quat_rotate(a[..., 3:], b[..., :3])
    return np.concatenate([xyz, quat_multiply(a[..., 3:], b[..., 3:])], axis=-1)


def invert(p: np.ndarray) -> np.ndarray:
    """T_ba from T_ab."""
    q_inv = quat_conjugate(p[..., 3:])
    return np.concatenate([-quat_rotate(q_inv, p[..., :3]), q_inv], axis=-1)


# --- collecting edges ----------------------------------------------------------------------------


def frame_id(name: str) -> str:
    """tf (ROS 1) allowed a leading slash; tf2 does not. Compare without it."""
    return name.lstrip("/")


@dataclass
class _EdgeLog:
    """Every update of one parent->child edge: the message it came in, its stamp, its pose."""

    message: array = field(default_factory=lambda: array("q"))
    stamp_ns: array = field(default_factory=lambda: array("q"))
    pose: array = field(default_factory=lambda: array("d"))  # 7 per update
    dynamic: bool = False  # published on a non-static topic at least once

    def poses(self) -> np.ndarray:
        return np.frombuffer(self.pose, dtype=np.float64).reshape(-1, 7)


class TfCollector:
    """The edges of a TF tree, as updated message by message in recorded order."""

    def __init__(self) -> None:
        self.edges: dict[tuple[str, str], _EdgeLog] = {}
        self.log_ns = array("q")  # per message fed in

    def add(self, msg: Any, log_ns: int, static: bool) -> None:
        index = len(self.log_ns)
        self.log_ns.append(log_ns)
        for tf in msg.transforms:
            key = (frame_id(tf.header.frame_id), frame_id(tf.child_frame_id))
            edge = self.edges.get(key)
            if edge is None:
                edge = self.edges[key] = _EdgeLog()
            s, t, r = tf.header.stamp, tf.transform.translation, tf.transform.rotation
            edge.message.append(index)
            edge.stamp_ns.append(s.sec * 1_000_000_000 + s.nanosec)
            edge.pose.extend((t.x, t.y, t.z, r.x, r.y, r.z, r.w))
            edge.dynamic = edge.dynamic or not static

    def parent_of(self) -> dict[str, str]:
        """child -> parent; a frame with two parents is not a tree and has no answer."""
        parents: dict[str, str] = {}
        for parent, child in self.edges:
            if parents.get(child, parent) != parent:
                raise SefaInputError(f"frame '{child}' has two parents in the TF data, "
                                     f"'{parents[child]}' and '{parent}'")
            parents[child] = parent
        return parents


# --- chains --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ChainStep:
    parent: str
    child: str
    inverted: bool  # walked child -> parent, so the edge's inverse is composed


def _to_root(frame: str, parents: dict[str, str]) -> list[str]:
    path = [frame]
    while path[-1] in parents and len(path) <= len(parents):
        path.append(parents[path[-1]])
    return path


def find_chain(parents: dict[str, str], source: str, target: str) -> list[ChainStep]:
    """The edges to compose, left to right, for the pose of `target` in `source`."""
    frames = set(parents) | set(parents.values())
    for name in (source, target):
        if name not in frames:
            listed = sorted(frames)
            more = f" and {len(listed) - 20} more" if len(listed) > 20 else ""
            raise SefaInputError(f"frame '{name}' is not in the TF data; frames: "
                                 f"{', '.join(listed[:20])}{more}")
    up_source, up_target = _to_root(source, parents), _to_root(target, parents)
    on_source = set(up_source)
    common = next((f for f in up_target if f in on_source), None)
    if common is None:
        raise SefaInputError(f"no TF chain from '{source}' to '{target}': they hang from "
                             f"different roots ('{up_source[-1]}' and '{up_target[-1]}')")
    up = up_source[:up_source.index(common)]
    down = up_target[:up_target.index(common)]
    return ([ChainStep(parents[f], f, True) for f in up]
            + [ChainStep(parents[f], f, False) for f in reversed(down)])


def compose_chain(edge_poses: list[np.ndarray], chain: list[ChainStep]) -> np.ndarray:
    """Compose per-sample edge poses (each (N, 7)) along the chain; identity for no edges."""
    n = edge_poses[0].shape[0] if edge_poses else 1
    out = np.tile(np.array([0, 0, 0, 0, 0, 0, 1.0]), (n, 1))
    for pose, step in zip(edge_poses, chain):
        out = compose(out, invert(pose) if step.inverted else pose)
    return out


# --- the stream ----------------------------------------------------------------------------------


def _static_sample(edges: list[_EdgeLog], log_ns: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """A chain of static edges only: one sample, when its last edge arrived."""
    last = max(edges, key=lambda e: e.message[-1])
    times = np.array([last.stamp_ns[-1]], dtype=np.int64)
    logs = np.array([log_ns[last.message[-1]]], dtype=np.int64)
    return times, logs, [e.poses()[-1:] for e in edges]


def _dynamic_samples(edges: list[_EdgeLog], log_ns: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """One sample per message that updates a dynamic edge of the chain, once all have values."""
    dynamic = [e for e in edges if e.dynamic]
    events = np.unique(np.concatenate([np.frombuffer(e.message, np.int64) for e in dynamic]))
    # each dynamic edge held at its latest update at or before each event
    latest = [np.searchsorted(np.frombuffer(e.message, np.int64), events, side="right") - 1
              for e in dynamic]
    valid = np.all([i >= 0 for i in latest], axis=0)
    events = events[valid]
    latest = [i[valid] for i in latest]
    # the sample's stamp: the newest stamp among the edges this very message updated
    stamp = np.full(events.shape, np.iinfo(np.int64).min, dtype=np.int64)
    for e, i in zip(dynamic, latest):
        updated = np.frombuffer(e.message, np.int64)[i] == events
        stamp = np.where(updated, np.maximum(stamp, np.frombuffer(e.stamp_ns, np.int64)[i]), stamp)
    held = {id(e): i for e, i in zip(dynamic, latest)}
    poses = [e.poses()[held[id(e)]] if e.dynamic else np.repeat(e.poses()[-1:], len(events), 0)
             for e in edges]
    return stamp, log_ns[events], poses


def tf_stream(tf: TfCollector, frames: list[str], *, key: str, topic: str,
              stamp: str = "auto") -> Stream:
    """The pose of ``frames[1]`` in ``frames[0]`` as a Stream of (N, 7) samples.

    `stamp` 'header' or 'auto' times each sample by the transforms' header stamps, 'log' by the
    recorder's time of the message that brought the update.
    """
    source, target = frame_id(frames[0]), frame_id(frames[1])
    try:
        chain = find_chain(tf.parent_of(), source, target)
    except SefaInputError as e:
        raise SefaInputError(e.what, key=key) from None
    edges = [tf.edges[(s.parent, s.child)] for s in chain]
    log_ns = np.frombuffer(tf.log_ns, np.int64)
    if not edges:  # a frame in itself: the identity, whenever the tree was seen
        times = logs = log_ns[:1].copy()
        values = np.tile(np.array([0, 0, 0, 0, 0, 0, 1.0]), (len(times), 1))
        return Stream(key, topic, times, values, list(POSE_NAMES), logs)
    sample = _dynamic_samples if any(e.dynamic for e in edges) else _static_sample
    stamps, logs, poses = sample(edges, log_ns)
    times = logs.copy() if stamp == "log" else stamps
    return Stream(key, topic, np.asarray(times, np.int64), compose_chain(poses, chain),
                  list(POSE_NAMES), np.asarray(logs, np.int64))
