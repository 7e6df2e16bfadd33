"""ROS 1 bags, ROS 2 bags and MCAP files to one `Stream` per topic-map feature.

All ROS data goes through rosbags' `AnyReader`: ROS 1 `.bag`, ROS 2 bag directories (sqlite3
or MCAP storage) and standalone `.db3` / `.mcap` files. A standalone MCAP with non-ROS
channels (JSON) is read with the `mcap` library instead; its ROS 2 CDR channels, if any, are
still deserialized by rosbags, from the schemas in the file, so a mixed file is one pass too.

Each file is read once, demultiplexing every wanted topic (a topic filter still decompresses
interleaved chunks, so a second pass would cost a second full read). Samples stay in recorded
order: `time_align` checks monotonicity and must be able to report stamps that go backwards.
Camera images are decoded in batches, by the reader or by worker processes (`image_decode`);
the frames are the same either way.

Errors are `SefaInputError`s naming the file, the key or topic, and the message: a missing,
truncated or corrupt file, a missing or silent topic, an unknown message type, an unknown field,
a value that changes shape.
"""

from __future__ import annotations

import contextlib
import json
import math
import operator
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Protocol

import numpy as np
from mcap.reader import make_reader
from mcap.records import Channel, Schema
from mcap.stream_reader import StreamReader
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from sefa_data.episode import Stream
from sefa_data.errors import SefaInputError
from sefa_data.readers.image_decode import (BATCH, IMAGE_TYPES, MIN_IMAGES_FOR_POOL, DecodePool,
                                            Encoded, encoded)
from sefa_data.readers.selectors import Selector, type_name
from sefa_data.readers.tf_lookup import STATIC_TOPIC, TfCollector, tf_stream
from sefa_data.readers.topic_map import FeatureSpec, StampSource, TopicMap
from sefa_data.validate import MAX_FPS, check_memory

SUFFIXES = (".bag", ".mcap", ".db3")
NS = 1_000_000_000

# --- errors --------------------------------------------------------------------------------------


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 200 else text[:197] + "..."


def _unreadable(path: Path, exc: BaseException, *, key: str | None = None,
                where: str | None = None) -> SefaInputError:
    """A library failed on the file's bytes: report it as a damaged file, in one line."""
    return SefaInputError(f"cannot read the recording (truncated or corrupt?): {_one_line(exc)}",
                          file=str(path), key=key, where=where)


def _at(index: int, log_ns: int) -> str:
    return f"message {index}, log time {log_ns / NS:.6f} s"


def _guard(items: Iterable[Any], path: Path) -> Iterator[Any]:
    """Iterate a library's message generator; its exceptions become one-line input errors."""
    it = iter(items)
    count = 0
    while True:
        try:
            item = next(it)
        except StopIteration:
            return
        except Exception as e:  # anything the library raises here is about the file's bytes
            raise _unreadable(path, e, where=f"message {count} of the file") from None
        count += 1
        yield item


# --- sources: one interface over AnyReader and the mcap library ----------------------------------


@dataclass(frozen=True)
class TopicInfo:
    msgtype: str
    count: int | None = None  # messages, when the file's index says


class Source(Protocol):
    path: Path
    format: str
    topics: dict[str, TopicInfo]

    def check_decodable(self, topic: str) -> None: ...

    def records(self, topics: set[str]) -> Iterator[tuple[str, int, bytes, Any]]:
        """(topic, log time ns, raw bytes, decode key) in recorded order."""
        ...

    def decode(self, raw: bytes, how: Any) -> Any: ...


class RosbagsSource:
    """Everything ROS, through rosbags' AnyReader."""

    def __init__(self, reader: AnyReader, path: Path):
        self.reader, self.path = reader, path
        self.format = _rosbags_format(path)
        self.topics = {name: TopicInfo(info.msgtype or "?", info.msgcount)
                       for name, info in reader.topics.items()}

    def check_decodable(self, topic: str) -> None:
        for conn in self.reader.topics[topic].connections:
            if conn.msgtype not in self.reader.typestore.fielddefs:
                raise SefaInputError(f"unknown message type '{conn.msgtype}': the recording "
                                     "carries no definition for it", file=str(self.path),
                                     key=topic)

    def records(self, topics: set[str]) -> Iterator[tuple[str, int, bytes, Any]]:
        conns = [c for c in self.reader.connections if c.topic in topics]
        if not conns:  # AnyReader reads every connection when given none
            return
        for conn, log_ns, raw in _guard(self.reader.messages(connections=conns), self.path):
            yield conn.topic, log_ns, raw, conn.msgtype

    def decode(self, raw: bytes, how: Any) -> Any:
        return self.reader.deserialize(raw, how)


class McapSource:
    """A standalone MCAP with non-ROS channels: JSON decoded here, ROS 2 CDR via rosbags."""

    def __init__(self, reader: Any, schemas: dict[int, Schema], channels: dict[int, Channel],
                 path: Path):
        self.reader, self.path = reader, path
        self.schemas, self.channels = schemas, channels
        encodings = {c.message_encoding for c in channels.values()}
        self.format = "mcap (" + ", ".join(sorted(encodings)) + ")"
        self.topics = {c.topic: TopicInfo(self._schema_name(c)) for c in channels.values()}
        self._typestore = _typestore_from_schemas(schemas.values())

    def _schema_name(self, channel: Channel) -> str:
        schema = self.schemas.get(channel.schema_id)
        return schema.name if schema is not None and schema.name else channel.message_encoding

    def check_decodable(self, topic: str) -> None:
        for ch in self.channels.values():
            if ch.topic != topic:
                continue
            if ch.message_encoding == "json":
                continue
            if ch.message_encoding == "cdr" and self._schema_name(ch) in self._typestore.fielddefs:
                continue
            raise SefaInputError(
                f"unknown message type '{self._schema_name(ch)}' ({ch.message_encoding} "
                "encoding): sefa reads JSON channels and ROS 2 CDR channels with ros2msg "
                "schemas from MCAP", file=str(self.path), key=topic)

    def records(self, topics: set[str]) -> Iterator[tuple[str, int, bytes, Any]]:
        if not topics:
            return
        messages = self.reader.iter_messages(topics=sorted(topics), log_time_order=True)
        for _, channel, message in _guard(messages, self.path):
            yield channel.topic, message.log_time, message.data, channel.id

    def decode(self, raw: bytes, how: Any) -> Any:
        channel = self.channels[how]
        if channel.message_encoding == "json":
            return json.loads(raw)
        return self._typestore.deserialize_cdr(raw, self._schema_name(channel))


def _typestore_from_schemas(schemas: Iterable[Schema]) -> Any:
    store = get_typestore(Stores.EMPTY)
    types: dict = {}
    for schema in schemas:
        if schema.encoding == "ros2msg":
            types.update(get_types_from_msg(schema.data.decode(), schema.name))
    store.register(types)
    return store


def _rosbags_format(path: Path) -> str:
    if path.suffix == ".bag":
        return "ros1 bag"
    if path.is_dir():
        storage = "mcap" if any(path.glob("*.mcap")) else "sqlite3"
        return f"ros2 bag ({storage})"
    return "ros2 mcap" if path.suffix == ".mcap" else "ros2 sqlite3"


def _mcap_layout(path: Path) -> tuple[dict[int, Schema], dict[int, Channel]] | None:
    """Schemas and channels of a standalone MCAP, or None when its bytes are not readable here
    (AnyReader then reports what is wrong with the file)."""
    try:
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
            if summary is not None:
                return summary.schemas, summary.channels
            f.seek(0)  # no summary section: the channels are only in the data
            schemas: dict[int, Schema] = {}
            channels: dict[int, Channel] = {}
            for rec in StreamReader(f).records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
            return schemas, channels
    except Exception:
        return None


def _is_ros_channel(channel: Channel, schemas: dict[int, Schema]) -> bool:
    schema = schemas.get(channel.schema_id)
    return channel.message_encoding == "cdr" and (
        schema is None or schema.encoding in ("ros2msg", "ros2idl", "omgidl"))


@contextlib.contextmanager
def open_source(path: str | Path) -> Iterator[Source]:
    """Open a recording for one pass; every failure is a one-line `SefaInputError`."""
    path = Path(path)
    if not path.exists():
        raise SefaInputError("no such file or directory", file=str(path))
    if path.is_file() and path.suffix not in SUFFIXES:
        raise SefaInputError(f"unsupported file type '{path.suffix}' (expected .bag, .mcap, "
                             ".db3 or a ROS 2 bag directory)", file=str(path))
    layout = _mcap_layout(path) if path.is_file() and path.suffix == ".mcap" else None
    if layout is not None and not all(_is_ros_channel(c, layout[0]) for c in layout[1].values()):
        with open(path, "rb") as f:
            try:
                source = McapSource(make_reader(f), layout[0], layout[1], path)
            except Exception as e:  # e.g. a ros2msg schema that does not parse
                raise _unreadable(path, e) from None
            yield source
        return
    try:
        # Old ROS 2 bags carry no message definitions; Humble's are the likeliest match.
        default = None if path.suffix == ".bag" else get_typestore(Stores.ROS2_HUMBLE)
        reader = AnyReader([path], default_typestore=default)
        reader.open()
    except Exception as e:
        raise _unreadable(path, e) from None
    try:
        yield RosbagsSource(reader, path)
    finally:
        reader.close()


# --- stamps --------------------------------------------------------------------------------------


def _dict_stamp(d: Any) -> int:
    return int(d["sec"]) * NS + int(d.get("nanosec", d.get("nsec", 0)))


def header_stamp_getter(msg: Any) -> Callable[[Any], int] | None:
    """How to read this message type's header stamp in ns, or None when it has none."""
    if isinstance(msg, dict):
        if isinstance(msg.get("header"), dict) and isinstance(msg["header"].get("stamp"), dict):
            return lambda m: _dict_stamp(m["header"]["stamp"])
        if isinstance(msg.get("timestamp"), dict):  # Foxglove JSON schemas
            return lambda m: _dict_stamp(m["timestamp"])
        return None
    header = getattr(msg, "header", None)
    if header is None or not hasattr(getattr(header, "stamp", None), "nanosec"):
        return None
    stamp = operator.attrgetter("header.stamp")

    def get(m: Any) -> int:
        s = stamp(m)
        return s.sec * NS + s.nanosec
    return get


def stamp_reader(msg: Any, mode: StampSource, key: str) -> Callable[[Any, int], int]:
    """(message, log time) -> the sample time the topic map asks for."""
    header = header_stamp_getter(msg)
    if mode == "log" or (mode == "auto" and header is None):
        return lambda m, log_ns: log_ns
    if header is None:
        raise SefaInputError(f"stamp is 'header' but {type_name(msg)} has no header; use "
                             "stamp: log (or auto)", key=key)

    def read(m: Any, log_ns: int) -> int:
        try:
            return header(m)
        except (AttributeError, KeyError, TypeError, ValueError):
            raise SefaInputError("message without a header stamp", key=key) from None
    return read


# --- sinks: what each feature keeps from the messages of its topic --------------------------------


class SampleSink:
    """One feature's samples: a selector's vectors or decoded images, with both timestamps."""

    def __init__(self, key: str, topic: str, stamp: StampSource,
                 value: Callable[[Any], np.ndarray]):
        self.key, self.topic, self.stamp, self.value = key, topic, stamp, value
        self._time: Callable[[Any, int], int] | None = None
        self.times: list[int] = []
        self.log_times: list[int] = []
        self.values: list[np.ndarray] = []

    def add(self, msg: Any, log_ns: int) -> None:
        if self._time is None:
            self._time = stamp_reader(msg, self.stamp, self.key)
        value = self.value(msg)
        self.times.append(self._time(msg, log_ns))
        self.log_times.append(log_ns)
        self.values.append(value)

    def stream(self, path: Path) -> Stream:
        return Stream(self.key, self.topic, np.array(self.times, dtype=np.int64),
                      _stack(self.values, self.log_times, self.key, path),
                      getattr(self.value, "names", None),
                      np.array(self.log_times, dtype=np.int64))


class ImageSink:
    """An image feature's samples. Messages are decoded in batches of `image_decode.BATCH`, by
    the reader or by the pool's worker processes (`image_decode.DecodePool`); `settle` gathers
    the frames in recorded order, so that where they were decoded changes nothing."""

    def __init__(self, key: str, topic: str, stamp: StampSource, size: list[int],
                 pool: DecodePool):
        self.key, self.topic, self.stamp = key, topic, stamp
        self.height, self.width = size
        self.pool = pool
        self._time: Callable[[Any, int], int] | None = None
        self.times: list[int] = []
        self.log_times: list[int] = []
        self._batch: list[Encoded] = []
        self._blocks: list[tuple[int, Any]] = []  # (index of the batch's first message, handle)
        self._checked = 0  # batches at the head of _blocks known to be finished and good
        self._frames: np.ndarray | None = None

    def add(self, msg: Any, log_ns: int) -> None:
        if self._time is None:
            self._time = stamp_reader(msg, self.stamp, self.key)
        try:
            image = encoded(msg, type_name(msg))
        except SefaInputError as e:
            raise SefaInputError(e.what, key=self.key) from None
        self.times.append(self._time(msg, log_ns))
        self.log_times.append(log_ns)
        self._batch.append(image)
        if len(self._batch) == BATCH:
            self._submit()
            if self._failed_so_far():
                raise _BadImage  # stop reading; `_settle` reports the image

    def _submit(self) -> None:
        start = len(self.times) - len(self._batch)
        self._blocks.append((start, self.pool.submit(self._batch, self.height, self.width)))
        self._batch = []

    def _failed_so_far(self) -> bool:
        """Whether a finished batch holds an image that does not decode (without waiting)."""
        while self._checked < len(self._blocks) and self._blocks[self._checked][1].done():
            if self._blocks[self._checked][1].result()[1] is not None:
                return True
            self._checked += 1
        return False

    def settle(self) -> tuple[int, SefaInputError] | None:
        """Wait for every batch. Returns (log time, error) of the first image that did not
        decode, or None."""
        if self._batch:
            self._submit()
        frames = []
        for start, handle in self._blocks:
            block, error = handle.result()
            if error is not None:
                i = start + error[0]
                return self.log_times[i], SefaInputError(error[1], key=self.key,
                                                         where=_at(i, self.log_times[i]))
            frames.append(block)
        self._blocks = []
        if frames:
            self._frames = frames[0] if len(frames) == 1 else np.concatenate(frames)
        return None

    def stream(self, path: Path) -> Stream:
        return Stream(self.key, self.topic, np.array(self.times, dtype=np.int64), self._frames,
                      None, np.array(self.log_times, dtype=np.int64))


class _BadImage(Exception):
    """An image sink met a batch with an image that does not decode (see `_settle`)."""


def _settle(images: list[ImageSink], path: Path) -> None:
    """Gather the frames of every image feature. Of the images that did not decode, report the
    one recorded first, as decoding them one by one while reading would have."""
    failed = [f for f in (sink.settle() for sink in images) if f is not None]
    if failed:
        error = min(failed, key=lambda f: f[0])[1]
        raise error.with_file(str(path))


def _stack(values: list[np.ndarray], log_times: list[int], key: str, path: Path) -> np.ndarray:
    try:
        return np.stack(values)
    except ValueError:
        pass
    first = values[0].shape
    i = next(i for i, v in enumerate(values) if v.shape != first)
    raise SefaInputError(f"value shape changes from {first} to {values[i].shape}",
                         file=str(path), key=key, where=_at(i, log_times[i]))


class TfSink:
    """Feeds a TF topic (or /tf_static) into the collector of one TF lookup."""

    def __init__(self, collector: TfCollector, static: bool):
        self.collector, self.static = collector, static

    def add(self, msg: Any, log_ns: int) -> None:
        self.collector.add(msg, log_ns, self.static)


def _is_tf_type(msgtype: str) -> bool:
    return msgtype.endswith(("/TFMessage", "/tfMessage"))  # tf2 and ROS 1 tf


@dataclass
class ReadPlan:
    """Which sinks each topic's messages go to."""

    sinks: dict[str, list[Any]] = field(default_factory=dict)
    samples: list[SampleSink | ImageSink] = field(default_factory=list)
    images: list[ImageSink] = field(default_factory=list)
    topic_of: dict[str, str] = field(default_factory=dict)  # feature key -> recorded topic
    lookups: list[tuple[str, FeatureSpec, TfCollector]] = field(default_factory=list)

    def add(self, topic: str, sink: Any) -> None:
        self.sinks.setdefault(topic, []).append(sink)


def resolve_topic(name: str, topics: Iterable[str]) -> str | None:
    """The recorded topic a map's name means: the same text, or else the one recorded with or
    without the leading '/' (ROS allows relative names, and a recorder may store either)."""
    topics = set(topics)
    if name in topics:
        return name
    other = name[1:] if name.startswith("/") else "/" + name
    return other if other in topics else None


def _plan(tmap: TopicMap, source: Source, pool: DecodePool) -> ReadPlan:
    plan = ReadPlan()
    collectors: dict[str, TfCollector] = {}
    static = resolve_topic(STATIC_TOPIC, source.topics)
    for key, spec in tmap.features.items():
        topic = resolve_topic(spec.topic, source.topics)
        if topic is None:
            if spec.optional:
                continue
            raise SefaInputError(f"topic {spec.topic} is not in the recording; it has: "
                                 f"{', '.join(sorted(source.topics)) or 'no topics'}",
                                 file=str(source.path), key=key)
        info = source.topics[topic]
        plan.topic_of[key] = topic
        source.check_decodable(topic)
        if spec.frames is not None:
            if not _is_tf_type(info.msgtype):
                raise SefaInputError(f"frames need a tf2_msgs/msg/TFMessage topic; "
                                     f"{topic} carries {info.msgtype}",
                                     file=str(source.path), key=key)
            if topic not in collectors:
                tf = collectors[topic] = TfCollector()
                plan.add(topic, TfSink(tf, static=topic == static))
                if topic != static and static is not None:
                    source.check_decodable(static)
                    plan.add(static, TfSink(tf, static=True))
            plan.lookups.append((key, spec, collectors[topic]))
            continue
        if spec.image_size and info.count:
            height, width = spec.image_size
            # decoded frames, then stacked into one array: twice the frames at the peak
            check_memory(2 * info.count * height * width * 3,
                         f"decoding {info.count} images at {height} x {width}",
                         file=str(source.path), key=key, hint="; choose a smaller image_size")
        if spec.image_size:
            sink = ImageSink(key, topic, tmap.stamp_of(spec), spec.image_size, pool)
            plan.images.append(sink)
        else:
            sink = SampleSink(key, topic, tmap.stamp_of(spec), Selector(spec.field, key))
        plan.samples.append(sink)
        plan.add(topic, sink)
    return plan


def _image_messages(tmap: TopicMap, source: Source) -> float:
    """How many images the map decodes from this file (inf when its index does not say)."""
    total = 0.0
    for spec in tmap.features.values():
        topic = resolve_topic(spec.topic, source.topics) if spec.image_size else None
        if topic is not None:
            count = source.topics[topic].count
            total += math.inf if count is None else count
    return total


# --- reading -------------------------------------------------------------------------------------


def read_streams(path: str | Path, tmap: TopicMap, decode_workers: int = 0
                 ) -> tuple[dict[str, Stream], np.ndarray]:
    """One Stream per feature of `tmap` (optional features whose topic is absent have none),
    and the log times of the split marker topic (empty when there is none).

    `decode_workers` processes decode camera images beside the reader (see `image_decode`);
    the streams are the same with any number. A file with fewer than MIN_IMAGES_FOR_POOL
    images is decoded in the reader alone, since starting the workers would cost more."""
    path = Path(path)
    with open_source(path) as source:
        if _image_messages(tmap, source) < MIN_IMAGES_FOR_POOL:
            decode_workers = 0
        with DecodePool(decode_workers) as pool:
            plan = _plan(tmap, source, pool)
            marker = resolve_topic(tmap.split.marker_topic, source.topics) \
                if tmap.split.marker_topic else None
            wanted = set(plan.sinks) | ({marker} if marker else set())
            counts, markers = _read(source, plan, wanted, marker)
    for key, spec in tmap.features.items():
        if not spec.optional and counts.get(plan.topic_of.get(key, spec.topic)) == 0:
            raise SefaInputError(f"topic {spec.topic} has no messages (silent)",
                                 file=str(path), key=key)
    streams = {s.key: s.stream(path) for s in plan.samples if s.times}
    for key, spec, collector in plan.lookups:
        if counts[plan.topic_of[key]]:
            stream = _lookup(key, spec, collector, tmap, path)
            if stream is not None:
                streams[key] = stream
    return ({k: streams[k] for k in tmap.features if k in streams},
            np.array(markers, dtype=np.int64))


def _read(source: Source, plan: ReadPlan, wanted: set[str], marker: str | None
          ) -> tuple[dict[str, int], list[int]]:
    """The one pass: decode each wanted message once and hand it to every sink of its topic.
    Returns the message count per topic and the marker topic's log times. Images are complete
    when it returns; an image that does not decode is reported before any later error."""
    try:
        counts, markers = _read_messages(source, plan, wanted, marker)
    except Exception:
        _settle(plan.images, source.path)  # raises when an earlier image did not decode
        raise
    _settle(plan.images, source.path)
    return counts, markers


def _read_messages(source: Source, plan: ReadPlan, wanted: set[str], marker: str | None
                   ) -> tuple[dict[str, int], list[int]]:
    counts = dict.fromkeys(wanted, 0)
    markers: list[int] = []
    sinks_of = plan.sinks
    for topic, log_ns, raw, how in source.records(wanted):
        index = counts[topic]
        counts[topic] = index + 1
        if topic == marker:
            markers.append(log_ns)
        sinks = sinks_of.get(topic)
        if sinks is None:
            continue
        try:
            msg = source.decode(raw, how)
        except Exception as e:  # the library's deserializer met bytes it cannot parse
            raise _unreadable(source.path, e, key=topic, where=_at(index, log_ns)) from None
        try:
            for sink in sinks:
                sink.add(msg, log_ns)
        except SefaInputError as e:
            raise SefaInputError(e.what, file=str(source.path), key=e.key or topic,
                                 where=_at(index, log_ns)) from None
    return counts, markers


def _lookup(key: str, spec: FeatureSpec, collector: TfCollector, tmap: TopicMap,
            path: Path) -> Stream | None:
    assert spec.frames is not None
    try:
        return tf_stream(collector, spec.frames, key=key, topic=spec.topic,
                         stamp=tmap.stamp_of(spec))
    except SefaInputError as e:
        if spec.optional:  # an optional key may be absent, and its frames with it
            return None
        raise e.with_file(str(path)) from None


# --- inspect -------------------------------------------------------------------------------------


@dataclass
class TopicSurvey:
    msgtype: str
    log_ns: list[int] = field(default_factory=list)
    skew_ns: list[int] = field(default_factory=list)  # header stamp - log time
    first: Any = None  # the first message, decoded (None when it cannot be)
    stamp: Callable[[Any], list[int]] | None = None  # header stamps of one message
    tf_edge: tuple[str, str] | None = None  # first transform of a dynamic TF topic


def _stamps_getter(msg: Any) -> Callable[[Any], list[int]] | None:
    """All header stamps in a message: its own, or each transform's in a TFMessage."""
    if not isinstance(msg, dict) and _is_tf_type(type_name(msg)):
        return lambda m: [t.header.stamp.sec * NS + t.header.stamp.nanosec for t in m.transforms]
    one = header_stamp_getter(msg)
    return None if one is None else (lambda m: [one(m)])


def survey(path: str | Path) -> tuple[str, dict[str, TopicSurvey]]:
    """One pass over every topic: log times, header-vs-log skew, and each topic's first message."""
    path = Path(path)
    with open_source(path) as source:
        topics = {t: TopicSurvey(info.msgtype) for t, info in source.topics.items()}
        decodable = set()
        for t in topics:
            with contextlib.suppress(SefaInputError):
                source.check_decodable(t)
                decodable.add(t)
        for topic, log_ns, raw, how in source.records(set(topics)):
            s = topics[topic]
            s.log_ns.append(log_ns)
            if topic not in decodable or (s.first is not None and s.stamp is None):
                continue
            try:
                msg = source.decode(raw, how)
            except Exception as e:
                raise _unreadable(path, e, key=topic, where=_at(len(s.log_ns) - 1, log_ns)
                                  ) from None
            if s.first is None:
                s.first, s.stamp = msg, _stamps_getter(msg)
                if s.stamp is None:
                    continue
            with contextlib.suppress(AttributeError, KeyError, TypeError, ValueError):
                s.skew_ns += [stamp - log_ns for stamp in s.stamp(msg)]
        fmt = source.format
    for topic, s in topics.items():
        if topic != STATIC_TOPIC and s.first is not None and s.stamp is not None \
                and _is_tf_type(s.msgtype) and s.first.transforms:
            tf = s.first.transforms[0]
            s.tf_edge = (tf.header.frame_id.lstrip("/"), tf.child_frame_id.lstrip("/"))
    return fmt, topics


def _seconds(ns: float | int) -> float:
    return round(float(ns) / NS, 6)


def _topic_summary(s: TopicSurvey) -> dict:
    t = np.asarray(s.log_ns, dtype=np.int64)
    span = int(t[-1] - t[0]) if len(t) > 1 else 0
    skew = np.asarray(s.skew_ns, dtype=np.float64) / NS
    return {
        "type": s.msgtype,
        "count": len(t),
        "rate_hz": round((len(t) - 1) / (span / NS), 3) if span > 0 else None,
        "max_gap_s": _seconds(np.diff(t).max()) if len(t) > 1 else None,
        "first_time_s": _seconds(t[0]) if len(t) else None,
        "last_time_s": _seconds(t[-1]) if len(t) else None,
        "skew_median_s": round(float(np.median(skew)), 6) if len(skew) else None,
        "skew_max_abs_s": round(float(np.abs(skew).max()), 6) if len(skew) else None,
    }


def inspect_recording(path: str | Path) -> dict:
    """Per topic: type, count, realised rate, largest gap, first/last time, clock skew."""
    fmt, topics = survey(path)
    summaries = {t: _topic_summary(s) for t, s in sorted(topics.items())}
    starts = [s["first_time_s"] for s in summaries.values() if s["count"]]
    ends = [s["last_time_s"] for s in summaries.values() if s["count"]]
    return {
        "path": str(path),
        "format": fmt,
        "message_count": sum(s["count"] for s in summaries.values()),
        "start_time_s": min(starts) if starts else None,
        "end_time_s": max(ends) if ends else None,
        "duration_s": round(max(ends) - min(starts), 6) if starts else None,
        "topics": summaries,
    }


# --- scaffold ------------------------------------------------------------------------------------

_SELECTORS = {  # a sensible first selector for common types (rosbags names ROS 1 types alike)
    "nav_msgs/msg/Odometry": ("pose.pose", "twist.twist for the velocities"),
    "geometry_msgs/msg/PoseStamped": ("pose", None),
    "geometry_msgs/msg/PoseWithCovarianceStamped": ("pose.pose", None),
    "geometry_msgs/msg/TwistStamped": ("twist", None),
    "geometry_msgs/msg/WrenchStamped": ("wrench", None),
    "geometry_msgs/msg/TransformStamped": ("transform", None),
}
_MARKER_TYPES = ("std_msgs/msg/Empty", "std_msgs/msg/Bool")
_MAX_DIMS = 64  # more is not a low-dimensional feature: the user should pick a field
_SKEW_LIMIT_S = 60.0


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_]+", "_", text.strip("/")).strip("_") or "topic"


def _q(text: str) -> str:
    return json.dumps(text)  # a JSON string is a valid YAML double-quoted scalar


@dataclass
class _Proposal:
    key: str
    lines: list[str]  # the feature's settings, YAML
    note: str | None = None


_LOG_TYPES = ("rosgraph_msgs/msg/Log", "rcl_interfaces/msg/Log", "rcl_interfaces/msg/ParameterEvent",
              "diagnostic_msgs/msg/DiagnosticArray", "rosgraph_msgs/msg/TopicStatistics")
_LOG_TOPICS = ("/rosout", "/rosout_agg", "/parameter_events", "/diagnostics", "/statistics")


def _propose(topic: str, s: TopicSurvey) -> _Proposal | str:
    """A feature for the topic, or why there is none."""
    msgtype, first = s.msgtype, s.first
    if not s.log_ns:
        return "no messages"
    if msgtype in _LOG_TYPES or topic in _LOG_TOPICS or topic.lstrip("/") in \
            [t.lstrip("/") for t in _LOG_TOPICS]:
        return "log and diagnostics messages, not robot data"
    if first is None:
        return "messages of this type cannot be decoded"
    if _is_tf_type(msgtype):
        if topic.lstrip("/") == STATIC_TOPIC.lstrip("/"):
            return "static transforms, used by every tf lookup"
        if s.tf_edge is None:
            return "no transforms"
        parent, child_frame = s.tf_edge
        return _Proposal(f"observation.{_slug(child_frame)}_pose",
                         [f"frames: [{_q(parent)}, {_q(child_frame)}]"],
                         "pose of the child in the parent frame: x y z qx qy qz qw")
    if len(s.log_ns) < 2:
        return f"too few messages ({len(s.log_ns)}) to resample at a frame rate"
    if msgtype in IMAGE_TYPES:
        return _Proposal(f"observation.images.{_slug(topic)}", ["image_size: [96, 96]"])
    if msgtype == "sensor_msgs/msg/JointState":
        names = list(first.name)
        if not names or len(first.position) != len(names):
            return "joint states without named positions"
        return _Proposal(f"observation.{_slug(topic)}",
                         [f"field: {_q('position[' + ', '.join(names) + ']')}"],
                         "velocity[...] and effort[...] pick the same way")
    text, note = _SELECTORS.get(msgtype, ("", None))
    try:
        values = Selector(text)(first)
    except SefaInputError as e:
        return e.what
    if values.size == 0:
        return "no numeric fields"
    if values.size > _MAX_DIMS:
        return f"{values.size} values per message; pick a field for a low-dimensional feature"
    return _Proposal(f"observation.{_slug(topic)}", [f"field: {_q(text)}"],
                     note or f"{values.size} values")


def _unique(key: str, taken: set[str]) -> str:
    out, n = key, 2
    while out in taken:
        out, n = f"{key}_{n}", n + 1
    taken.add(out)
    return out


def scaffold_topic_map(path: str | Path, fps: float | None = None) -> str:
    """A commented starter topic map (YAML) for the recording's topics (see
    `scaffold_topic_map_noted`)."""
    return scaffold_topic_map_noted(path, fps)[0]


# in a scaffold where no topic ingests as it is: where to select a field, in the map itself
_TEMPLATE = ["  # No topic ingests as it is: each one is listed under \"Not mapped\" below with the",
             "  # reason. To map one, uncomment these lines, name its topic and a numeric field of",
             "  # its message (a dotted path to a number or to an array of numbers, e.g.",
             "  # pose.position, or a name pick such as position[joint_a, joint_b]), then",
             "  # `sefa ingest RECORDING --map THIS_FILE`.",
             "  # action:",
             "  #   topic: /TOPIC",
             "  #   field: FIELD"]


def scaffold_topic_map_noted(path: str | Path, fps: float | None = None
                             ) -> tuple[str, str | None]:
    """A commented starter topic map (YAML) for the recording's topics, and a warning when no
    topic could be mapped.

    The map is checked the way `sefa ingest` reads it: a feature whose data the ingest refuses
    (NaN values, a value that changes shape, a silent stretch, ...) is left out, with the
    reason in the map's comments, until the map ingests as it is. When that leaves no feature
    (every message a list of messages, say), the map is still written, each topic's reason in
    it and a commented feature to fill in: "select a numeric field" then has a place to go."""
    path = Path(path)
    _, topics = survey(path)
    summaries = {t: _topic_summary(s) for t, s in topics.items()}
    proposals: list[tuple[str, _Proposal]] = []
    skipped: list[str] = []
    for topic in sorted(topics):
        p = _propose(topic, topics[topic])
        if isinstance(p, str):
            skipped.append(f"#   {topic} ({topics[topic].msgtype}): {p}")
        else:
            proposals.append((topic, p))
    note = None
    while True:
        if not proposals:
            if not topics:
                raise SefaInputError("the recording has no topics", file=str(path))
            text, _ = _scaffold_text(path, topics, summaries, [], skipped, fps, note)
            at = text.index("features:\n") + len("features:\n")
            text = text[:at] + "\n".join(_TEMPLATE) + "\n" + text[at:]
            return text, (f"warning: no topic of {path.name} ingests as a feature as it is "
                          f"({len(skipped)} listed in the map with the reason): the map names "
                          "no feature yet; in it, select a numeric field of a topic (the "
                          "commented `field:`) and ingest with --map")
        text, keys = _scaffold_text(path, topics, summaries, proposals, skipped, fps, note)
        problem = _ingest_problem(path, text)
        if problem is None:
            return text, None
        key, what = problem
        bad = next((i for i, k in enumerate(keys) if k == key), None)
        if bad is None:  # not one feature's fault; say so rather than guess
            if note is not None:
                return text, None
            note = f"# NOTE: `sefa ingest` with this map fails: {what}"
            continue
        topic, _ = proposals.pop(bad)
        skipped.append(f"#   {topic} ({topics[topic].msgtype}): {what}")


def _ingest_problem(path: Path, text: str) -> tuple[str | None, str] | None:
    """(feature key or None, what is wrong) when ingesting with the map `text` fails."""
    import yaml

    from sefa_data.config_io import from_dict
    from sefa_data.readers.time_align import align_streams

    tmap = from_dict(TopicMap, yaml.safe_load(text))
    try:
        streams, markers = read_streams(path, tmap)
        for key, stream in streams.items():
            values = stream.values.reshape(len(stream.values), -1)
            if len(values) > 1 and not tmap.features[key].is_image and (values == values[0]).all():
                return key, f"only constants: every value is the same in all {len(values)} messages"
        align_streams(streams, tmap, str(path), markers)
    except SefaInputError as e:
        for key, spec in tmap.features.items():
            if e.key in (key, spec.topic) or (e.key or "").startswith(key + " ("):
                return key, e.what + (f" (at {e.where})" if e.where else "")
        return None, e.what
    return None


def _scaffold_text(path: Path, topics: dict[str, TopicSurvey], summaries: dict,
                   proposals: list[tuple[str, _Proposal]], skipped: list[str],
                   fps: float | None, note: str | None) -> tuple[str, list[str]]:
    rates = [(summaries[t]["rate_hz"], t) for t, _ in proposals if summaries[t]["rate_hz"]]
    if fps is not None:
        fps_line = f"fps: {fps:g}"
    elif rates:
        rate, fastest = max(rates)
        fps_line = (f"fps: {min(max(1, round(rate)), int(MAX_FPS))}  # the fastest feature "
                    f"topic, {fastest}, runs at {rate:g} Hz")
    else:
        fps_line = "fps: 10  # no topic has a measurable rate; set the rate you want"
    skewed = [t for t, _ in proposals
              if abs(summaries[t]["skew_median_s"] or 0.0) > _SKEW_LIMIT_S]
    if skewed:
        skew = summaries[skewed[0]]["skew_median_s"]
        stamp_lines = [f"# Header stamps of {', '.join(skewed)} are {skew:+.0f} s off the",
                       "# recorder's clock (simulation time?): every feature is timed by",
                       "# the log time instead.",
                       "stamp: log"]
    else:
        stamp_lines = ["stamp: auto  # header stamp when a message has one, else the log time"]

    out = [f"# sefa topic map scaffolded from {path.name}.",
           "# Rename the keys to what your policy expects (Diffusion Policy: `action`,",
           "# `observation.state`, ...), delete what you do not need, and mark features",
           "# that may be absent with `optional: true`. A field is a dotted path (pose.pose),",
           "# a name pick (position[joint_a, joint_b]) or \"\" for the whole message.",
           *([note] if note else []),
           fps_line, *stamp_lines, f"max_stamp_skew_s: {_SKEW_LIMIT_S}", "features:"]
    taken: set[str] = set()
    keys = []
    for topic, p in proposals:
        sm = summaries[topic]
        rate = f", {sm['rate_hz']:g} Hz" if sm["rate_hz"] else ""
        out.append(f"  # {topic}: {sm['type']}, {sm['count']} messages{rate}"
                   + (f"; {p.note}" if p.note else ""))
        keys.append(_unique(p.key, taken))
        out.append(f"  {_q(keys[-1])}:")
        out += [f"    topic: {_q(topic)}"] + [f"    {line}" for line in p.lines]
    if "action" not in keys:  # the key `sefa train` trains on: the map must name it
        out.insert(out.index("features:"),
                   "# TODO: no feature is named `action`, the key `sefa train` trains on: rename "
                   "the\n# commanded topic's key below to `action`.")
    if skipped:
        out += ["# Not mapped:", *skipped]
    markers = [t for t, s in topics.items() if s.msgtype in _MARKER_TYPES]
    out += ["# split:",
            "#   gap_s: 2.0  # a new episode after a silence longer than this",
            f"#   marker_topic: {markers[0] if markers else '/episode_start'}"
            "  # a new episode at each message"]
    return "\n".join(out) + "\n", keys
