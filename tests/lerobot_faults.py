"""Bad LeRobot datasets made from good ones, for tests/sefa_data_tests/test_lerobot_reader_faults.py and the
bad-input catalogue (tests/bad_inputs.py, docs/bad_input_catalogue.md).

Each is a copy of a real dataset edited with pyarrow and json: the Push-T image fixture in
../shared/data (written by LeRobot 0.6.1), or the small v2.1 dataset that tests/sefa_data_tests/test_lerobot.py
writes with pyarrow and PyAV. The tasks tables indexed by task in tests/data/lerobot_tasks
were written by pandas itself (its make_tasks.py: the project does not depend on pandas).
"""

from __future__ import annotations

import io
import json
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

IMAGES = "lerobot_pusht5_image_v30"
TASKS = Path(__file__).resolve().parent / "data" / "lerobot_tasks"
EPISODES = "meta/episodes/chunk-000/file-000.parquet"
DATA = "data/chunk-000/file-000.parquet"


def image_copy(shared_data: Path, tmp: Path, name: str = "ds") -> Path:
    root = tmp / name
    shutil.copytree(shared_data / IMAGES, root)
    return root


def edit_info(root: Path, edit) -> None:
    info = json.loads((root / "meta/info.json").read_text())
    edit(info)
    (root / "meta/info.json").write_text(json.dumps(info))


def edit_episodes(root: Path, column: str, row: int, value) -> None:
    table = pq.read_table(root / EPISODES)
    values = table.column(column).to_pylist()
    values[row] = value
    i = table.schema.get_field_index(column)
    pq.write_table(table.set_column(i, pa.field(column, table.schema.field(column).type),
                                    pa.array(values, table.schema.field(column).type)),
                   root / EPISODES)


def split_in_two_data_files(root: Path) -> None:
    """The fixture's one data file as two (episodes 0-2, 3-4), its episodes table to match:
    the layout LeRobot writes past data_files_size_in_mb."""
    data = pq.read_table(root / DATA)
    eps = pq.read_table(root / EPISODES)
    cut = eps.column("dataset_from_index")[3].as_py()
    pq.write_table(data.slice(0, cut), root / DATA)
    pq.write_table(data.slice(cut), root / "data/chunk-000/file-001.parquet")
    i = eps.schema.get_field_index("data/file_index")
    pq.write_table(eps.set_column(i, eps.schema.field(i), pa.array([0, 0, 0, 1, 1], pa.int64())),
                   root / EPISODES)


def flip_bit_on_disk(path: Path, column: str, row: int, bit: int) -> tuple[float, float]:
    """Rewrite the parquet uncompressed and plain-encoded (so that a value's four bytes are in
    the file as they are), then flip one bit of one float32 value in the file's bytes, as a
    flip on disk would: parquet pages carry no checksum."""
    table = pq.read_table(path)
    pq.write_table(table, path, compression="NONE", use_dictionary=False,
                   write_statistics=False)
    values = table.column(column).combine_chunks().flatten().to_numpy()
    width = len(values) // table.num_rows
    raw = path.read_bytes()
    for i in range(row * width, len(values)):  # a value whose bytes occur once in the file
        pattern = values[i:i + 1].tobytes()
        if raw.count(pattern) == 1:
            break
    at = raw.index(pattern)
    word = np.frombuffer(pattern, np.uint32)[0] ^ np.uint32(1 << bit)
    path.write_bytes(raw[:at] + np.uint32(word).tobytes() + raw[at + 4:])
    return float(values[i]), float(np.uint32(word).view(np.float32))


def _png(h: int, w: int) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.zeros((h, w, 3), np.uint8)).save(buf, format="PNG")
    return buf.getvalue()


def _other_size_png(root: Path) -> None:
    table = pq.read_table(root / DATA)
    cells = table.column("observation.image").to_pylist()
    cells[5] = {**cells[5], "bytes": _png(64, 64)}
    i = table.schema.get_field_index("observation.image")
    pq.write_table(table.set_column(i, table.schema.field(i),
                                    pa.array(cells, table.schema.field(i).type)), root / DATA)


def _info_edit(edit):
    return lambda root: edit_info(root, edit)


MALFORMED = {
    # name: (edit of the image fixture, the file named, the key named, words of the line)
    "total_frames many": (_info_edit(lambda i: i.update(total_frames="many")), "meta/info.json",
                          "total_frames", "must be a whole number, got 'many'"),
    "total_episodes null": (_info_edit(lambda i: i.update(total_episodes=None)),
                            "meta/info.json", "total_episodes", "must be a whole number, got None"),
    "a feature that is not a mapping": (
        _info_edit(lambda i: i["features"].update(action="float32")), "meta/info.json",
        "features.action", "must be a mapping with dtype and shape, got 'float32'"),
    "shape two": (_info_edit(lambda i: i["features"]["action"].update(shape="two")),
                  "meta/info.json", "features.action.shape",
                  "must be a list of whole numbers, got 'two'"),
    "a malformed data_path": (
        _info_edit(lambda i: i.update(data_path="data/chunk-{chunk_index:03d/file.parquet")),
        "meta/info.json", "data_path", "malformed path template"),
    "a template field LeRobot does not fill": (
        _info_edit(lambda i: i.update(data_path="data/{episode_chunk}/file-{file_index}.parquet")),
        "meta/info.json", "data_path", "uses {episode_chunk}, not a field LeRobot fills"),
    "length null in the episodes table": (
        lambda root: edit_episodes(root, "length", 1, None), EPISODES, "length",
        "must be a whole number, got None (at row 1)"),
    "one PNG of another size": (_other_size_png, DATA, "observation.image",
                                "an image of 64x64 where the episode's first is 96x96"),
    "image shape in info.json not the frames'": (
        _info_edit(lambda i: i["features"]["observation.image"].update(shape=[84, 84, 3])),
        DATA, "observation.image", "frames of 96x96 (height x width) where info.json's shape is "
        "[84, 84, 3]"),
}


def nan_timestamp(path: Path, frame: int) -> None:
    table = pq.read_table(path)
    ts = table.column("timestamp").to_numpy().copy()
    ts[frame] = np.nan
    i = table.schema.get_field_index("timestamp")
    pq.write_table(table.set_column(i, table.schema.field(i), pa.array(ts)), path)


# --------------------------------------------------------------------------- the catalogue


def lerobot_cases(shared: Path) -> list:
    """The reader's cases of the bad-input catalogue: `sefa ingest DATASET --out new.zarr`."""
    from bad_inputs import Case, Run
    from test_lerobot import write_v21

    if not (shared / IMAGES).is_dir():
        return upload_cases()
    v21 = "pyarrow + PyAV (tests/sefa_data_tests/test_lerobot.py's v2.1 writer)"
    fixture = f"shared data ({IMAGES}), pyarrow / json edit"

    def ingest(make_root, *extra):
        def make(_, d: Path) -> Run:
            root = make_root(d)
            return Run(["ingest", root, "--out", d / "new.zarr", *extra], d / "new.zarr")
        return make

    def image(damage):
        def go(d: Path) -> Path:
            root = image_copy(shared, d)
            damage(root)
            return root
        return go

    def small(damage, **kw):
        def go(d: Path) -> Path:
            root = d / "v21"
            write_v21(root, **kw)
            damage(root)
            return root
        return go

    def tasks_by_pandas(root: Path) -> None:
        shutil.copy(TASKS / "tasks_unnamed_index.parquet", root / "meta/tasks.parquet")

    def chunk_index(root: Path) -> None:
        edit_info(root, lambda i: i.update(
            data_path="data/chunk-{chunk_index:03d}/episode_{episode_index:06d}.parquet",
            video_path="videos/chunk-{chunk_index:03d}/{video_key}/episode_{file_index:06d}.mp4"))

    def wrong_file_index(root: Path) -> None:
        split_in_two_data_files(root)
        edit_episodes(root, "data/file_index", 3, 0)

    k = "7 LeRobot"
    written = dict(exit=0, store="written", fragments=("frames appended",))
    refused = dict(store="not created")
    cases = [
        Case("LeRobot: meta/tasks.parquet written by pandas with the task as its (unnamed) index",
             k, "pandas (tests/data/lerobot_tasks)", ingest(image(tasks_by_pandas)), **written),
        Case("LeRobot v2.1: path templates with {chunk_index} and {file_index}", k, v21,
             ingest(small(chunk_index)), **written),
        Case("LeRobot v2.0 (v2.1 without per-episode statistics)", k, v21,
             ingest(small(lambda r: edit_info(r, lambda i: i.update(codebase_version="v2.0")))),
             **written),
        Case("LeRobot: the last episode's video missing (found before any decoding)", k, v21,
             ingest(small(lambda r: (r / "videos/chunk-000/observation.images.cam/"
                                          "episode_000002.mp4").unlink(), lengths=(6, 5, 7))),
             fragments=("episode_000002.mp4: observation.images.cam: missing video file",),
             **refused),
        Case("LeRobot: a data parquet missing", k, v21,
             ingest(small(lambda r: (r / "data/chunk-000/episode_000001.parquet").unlink())),
             fragments=("episode_000001.parquet: missing",), **refused),
        *[Case(f"LeRobot: a float action declared {t} in info.json", k, fixture,
               ingest(image(lambda r, t=t: edit_info(
                   r, lambda i: i["features"]["action"].update(dtype=t))))
               , fragments=(f"action: info.json's dtype {t} cannot hold these values",
                            "--allow-lossy-cast"), **refused) for t in ("int8", "uint8")],
        Case("the same (uint8) with --allow-lossy-cast", k, fixture,
             ingest(image(lambda r: edit_info(r, lambda i: i["features"]["action"].update(
                 dtype="uint8"))), "--allow-lossy-cast"), **written),
        Case("LeRobot: one flipped exponent bit of an action in the data parquet (on disk)", k,
             fixture, ingest(image(lambda r: flip_bit_on_disk(r / DATA, "action", 170, 29))),
             fragments=("action: value", "as read but", "own statistics", "episode 1"),
             **refused),
        Case("LeRobot: a NaN timestamp", k, v21,
             ingest(small(lambda r: nan_timestamp(r / "data/chunk-000/episode_000001.parquet",
                                                  4))),
             fragments=("timestamp: timestamp nan is not a finite", "frame 4"), **refused),
        *[Case(f"LeRobot: {name}", k, fixture, ingest(image(damage)),
               fragments=(f"{file}: {key}: ", words), **refused)
          for name, (damage, file, key, words) in MALFORMED.items()],
        Case("LeRobot v2.1: video_path null with a video feature", k, v21,
             ingest(small(lambda r: edit_info(r, lambda i: i.update(video_path=None)))),
             fragments=("info.json: video_path: must be a path template",), **refused),
        Case("LeRobot: a wrong data/file_index (two data files)", k, fixture,
             ingest(image(wrong_file_index)),
             fragments=("data/file_index: episode 3 points to data/chunk-000/file-000.parquet",
                        "its rows are in data/chunk-000/file-001.parquet"), **refused),
    ]
    return cases + upload_cases()


def upload_cases() -> list:
    """Datasets as others publish them (issues 46 and 49), written with pyarrow and PyAV by
    LeRobot 0.6.1's layout (tests/lerobot_v30.py): no shared data needed."""
    from bad_inputs import Case, Run
    from lerobot_v30 import EPISODES as EPISODES30, lfs_pointer, video_file, write_v30
    from lerobot_v30 import DATA as DATA30
    from test_lerobot import write_v21

    made = "pyarrow + PyAV (tests/lerobot_v30.py, LeRobot 0.6.1's v3.0 layout)"
    v21 = "pyarrow + PyAV (tests/sefa_data_tests/test_lerobot.py's v2.1 writer)"
    cams = ("observation.images.a", "observation.images.b")

    def ingest(make_root, *extra):
        def make(_, d: Path) -> Run:
            return Run(["ingest", make_root(d), "--out", d / "new.zarr", *extra], d / "new.zarr")
        return make

    def inspect(make_root):
        def make(_, d: Path) -> Run:
            return Run(["inspect", make_root(d)], d / "new.zarr")
        return make

    def v30(damage=lambda root: None, **kw):
        def go(d: Path) -> Path:
            write_v30(d / "ds", **kw)
            damage(d / "ds")
            return d / "ds"
        return go

    def tables_only(root: Path) -> None:
        for folder in ("data", "videos"):
            shutil.rmtree(root / folder)

    def seven_videos(d: Path) -> Path:
        write_v21(d / "v21", lengths=(3,) * 8)
        for e in range(1, 8):
            (d / f"v21/videos/chunk-000/observation.images.cam/episode_{e:06d}.mp4").unlink()
        return d / "v21"

    def pointers(root: Path) -> None:
        lfs_pointer(root / DATA30)
        lfs_pointer(video_file(root, "observation.images.cam"))

    def no_from_timestamp(root: Path) -> None:
        table = pq.read_table(root / EPISODES30)
        pq.write_table(table.drop(["videos/observation.images.b/from_timestamp"]),
                       root / EPISODES30)

    def damaged_table(root: Path) -> None:
        (root / EPISODES30).write_bytes((root / EPISODES30).read_bytes()[:200])

    k = "7 LeRobot"
    written = dict(exit=0, store="written", fragments=("frames appended",))
    refused = dict(store="not created")
    return [
        Case("LeRobot: an action declared [1, 2] (a leading axis of 1, LeRobot's Array2D)", k,
             made, ingest(v30(action_shape=(1, 2))), **written),
        Case("LeRobot: an upload of the tables alone (no data/, no videos/), inspected", k, made,
             inspect(v30(tables_only, cameras=cams)),
             fragments=("3 files the episodes table points to are missing (1 data parquet file "
                        "and 2 video files)", "no data/ and no videos/ folder"), **refused),
        Case("LeRobot: seven of eight videos missing (all named in one run)", k, v21,
             ingest(seven_videos),
             fragments=("7 files the episodes table points to are missing (7 video files)",
                        "episode_000003.mp4 and 4 more"), **refused),
        Case("LeRobot: a clone without Git LFS (the parquet and mp4 files are pointers)", k, made,
             ingest(v30(pointers)),
             fragments=("2 files are Git LFS pointers, not the files themselves",
                        "run `git lfs pull` inside the clone"), **refused),
        Case("LeRobot: a damaged episodes table (pyarrow's long message cut at a word)", k, made,
             ingest(v30(damaged_table)),
             fragments=("unreadable parquet (Could not open Parquet input source",
                        " ...): truncated or damaged"), **refused),
        Case("LeRobot: an episodes table without videos/CAM/from_timestamp", k, made,
             ingest(v30(no_from_timestamp, cameras=cams)),
             fragments=("observation.images.b: the episodes table has no column "
                        "videos/observation.images.b/from_timestamp",
                        "leave it out with --key"), **refused),
        Case("the same with --key leaving that camera out", k, made,
             ingest(v30(no_from_timestamp, cameras=cams), "--key", "observation.state", "--key",
                    "action", "--key", "observation.images.a"), exit=0, store="written",
             fragments=("skipped key observation.images.b: not among the --key choices",)),
    ]
