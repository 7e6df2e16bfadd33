"""The bad-input catalogue of issue 12: every case run through the real `sefa` CLI in a child
process, with its exit status, its last stderr line and whether the store was left unchanged.

Used by tests/sefa_data_tests/test_bad_input_catalogue.py (every case must end as it says) and by
benchmarks/bad_input_catalogue.py (prints the table for docs/bad_input_catalogue.md).

Inputs are made here with the libraries' own writers (h5py, zarr, rosbags) in a temporary
folder, or derived from ../shared/data (the handover file); each case says which.
"""

from __future__ import annotations

import ctypes
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import h5py
import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"

# a child that runs `main()` after a patch (how an EIO from the disk is simulated)
_RUNNER = "import sys\n{patch}\nfrom sefa_cli.main import main\nsys.argv = ['sefa'] + sys.argv[1:]\nmain()\n"
EIO_PATCH = (
    "import errno, h5py\n"
    "def _eio(self, *a, **k):\n"
    "    raise OSError(errno.EIO, 'Input/output error')\n"
    "h5py.Dataset.__getitem__ = _eio\n")


@dataclass
class Run:
    args: list
    watch: Path  # the store: it must be byte-identical afterwards (or, if new, not appear)
    env: dict = field(default_factory=dict)
    patch: str = ""
    no_dac: bool = False  # run without root's permission override (read-only cases)


@dataclass
class Case:
    name: str
    klass: str  # the issue's build point
    source: str  # where the input comes from
    make: Callable[["Inputs", Path], Run]
    exit: int = 1
    fragments: tuple[str, ...] = ()  # in the last stderr line
    store: str = "unchanged"  # or "written": the expected outcome for the watched store
    before: Callable[["Inputs", Path], list[Run]] | None = None  # runs that set the case up


@dataclass
class Result:
    case: Case
    exit: int
    line: str
    stderr: str
    stdout: str
    store: str  # unchanged | not created | written | changed


# --------------------------------------------------------------------------- inputs

def write_demos(path: Path, seed: int = 0, lengths=(6, 9), **edits) -> Path:
    """A robomimic-layout HDF5 file (h5py): actions, obs/state, obs/cam_image per demo."""
    rng = np.random.default_rng(seed)
    with h5py.File(path, "w") as f:
        for i, n in enumerate(lengths):
            g = f.create_group(f"data/demo_{i}")
            g["actions"] = rng.normal(size=(n, 2)).astype(np.float32)
            g["obs/state"] = rng.normal(size=(n, 3)).astype(np.float32)
            g["obs/cam_image"] = rng.integers(0, 256, (n, 16, 16, 3), dtype=np.uint8)
        if "total" in edits:
            f["data"].attrs["total"] = edits["total"]
        if "state_rows" in edits:  # one demo whose observation is longer than its actions
            del f["data/demo_1/obs/state"]
            f["data/demo_1/obs/state"] = np.zeros((edits["state_rows"], 3), np.float32)
        if "actions" in edits:
            for i in range(len(lengths)):
                del f[f"data/demo_{i}/actions"]
                f[f"data/demo_{i}/actions"] = edits["actions"]
    return path


def write_bag(path: Path, n_joint: int = 200, n_images: int = 0) -> Path:
    """A rosbag2 (MCAP storage) with /joint_states at 100 Hz and optional 8x8 /cam images,
    written with rosbags' writer."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    t0 = 1_700_000_000 * 10**9

    def header(ns):
        return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
            sec=ns // 10**9, nanosec=ns % 10**9), frame_id="")

    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        js = w.add_connection("/joint_states", "sensor_msgs/msg/JointState", typestore=ts)
        cam = w.add_connection("/cam", "sensor_msgs/msg/Image", typestore=ts) if n_images else None
        for i in range(n_joint):
            ns = t0 + i * 10_000_000
            w.write(js, ns, ts.serialize_cdr(T["sensor_msgs/msg/JointState"](
                header=header(ns), name=["a", "b"], position=np.array([0.3 + i * 0.01, -0.2]),
                velocity=np.zeros(0), effort=np.zeros(0)), js.msgtype))
            if cam is not None and i < n_images:
                w.write(cam, ns, ts.serialize_cdr(T["sensor_msgs/msg/Image"](
                    header=header(ns), height=8, width=8, encoding="rgb8", is_bigendian=0,
                    step=24, data=np.zeros(192, np.uint8)), cam.msgtype))
    return path


MAP = "fps: 10\nfeatures:\n  observation.state: {topic: /joint_states, field: position}\n"


class Inputs:
    """Shared inputs, made once; each case works on its own copies."""

    def __init__(self, root: Path):
        from sefa_data.ingest import IngestOptions, ingest

        self.root = root
        self.a = write_demos(root / "a.hdf5", 0)
        self.b = write_demos(root / "b.hdf5", 1, lengths=(5, 7))
        self.bag = write_bag(root / "bag")
        self.base = root / "base.zarr"
        ingest([self.a], self.base, IngestOptions(fps=10))
        self.ros_base = root / "ros_base.zarr"
        m = root / "map.yaml"
        m.write_text(MAP)
        ingest([self.bag], self.ros_base, IngestOptions(topic_map=str(m)))
        after = root / "after.zarr"
        shutil.copytree(self.base, after)
        ingest([self.b], after, IngestOptions())
        self._states = {"before": snapshot(self.base), "after": snapshot(after)}

    def state(self, name: str) -> dict[str, bytes]:
        """The base store's bytes before ("before") or after ("after") appending b.hdf5."""
        return self._states[name]

    def store(self, d: Path, ros: bool = False) -> Path:
        out = d / "store.zarr"
        shutil.copytree(self.ros_base if ros else self.base, out)
        return out

    @staticmethod
    def map(d: Path, text: str, name: str = "map.yaml") -> Path:
        (d / name).write_text(text)
        return d / name


# --------------------------------------------------------------------------- cases

def _ingest_b(i: Inputs, d: Path, damage: Callable[[Path], None], *extra) -> Run:
    s = i.store(d)
    damage(s)
    return Run(["ingest", i.b, "--out", s, *extra], s)


def _inspect(i: Inputs, d: Path, damage: Callable[[Path], None], *extra) -> Run:
    s = i.store(d)
    damage(s)
    return Run(["inspect", s, *extra], s)


def _rm(rel: str) -> Callable[[Path], None]:
    def go(s: Path) -> None:
        p = s / rel
        shutil.rmtree(p) if p.is_dir() else p.unlink()
    return go


def _truncate(rel: str, size: int) -> Callable[[Path], None]:
    def go(s: Path) -> None:
        with open(s / rel, "r+b") as f:
            f.truncate(size)
    return go


def _flip_byte(rel: str) -> Callable[[Path], None]:
    def go(s: Path) -> None:
        data = bytearray((s / rel).read_bytes())
        data[len(data) // 2] ^= 0xFF
        (s / rel).write_bytes(bytes(data))
    return go


def _attrs(edit: Callable[[dict], None] | None, text: str | None = None) -> Callable[[Path], None]:
    def go(s: Path) -> None:
        if text is not None:
            (s / ".zattrs").write_text(text)
            return
        attrs = json.loads((s / ".zattrs").read_text())
        edit(attrs)
        (s / ".zattrs").write_text(json.dumps(attrs))
    return go


def _garbage_journal(s: Path) -> None:
    (s / ".sefa-journal" / "files").mkdir(parents=True)
    (s / ".sefa-journal" / "listing.json").write_text("{not json")


def _pickle_codec(rel: str) -> Callable[[Path], None]:
    def go(s: Path) -> None:
        meta = json.loads((s / rel).read_text())
        meta["filters"] = [{"id": "pickle", "protocol": 5}]
        (s / rel).write_text(json.dumps(meta))
    return go


def _read_only(s: Path) -> None:
    for p in [s, *s.rglob("*")]:
        p.chmod(0o555 if p.is_dir() else 0o444)


def _new_from(i: Inputs, d: Path, inp: Path, *extra) -> Run:
    return Run(["ingest", inp, "--out", d / "new.zarr", *extra], d / "new.zarr")


def _bag_map(text: str) -> Callable[[Inputs, Path], Run]:
    def make(i: Inputs, d: Path) -> Run:
        return Run(["ingest", i.bag, "--map", Inputs.map(d, text), "--out", d / "new.zarr"],
                   d / "new.zarr")
    return make


def _zarr_input(d: Path, extra: Callable[["object"], None]) -> Path:
    import zarr

    root = zarr.open_group(str(d / "in.zarr"), mode="w", zarr_format=2)
    root.create_array("data/action", data=np.arange(8, dtype=np.float32).reshape(4, 2))
    root.create_array("meta/episode_ends", data=np.array([4], np.int64))
    extra(root)
    return d / "in.zarr"


def _zarr_strings(i: Inputs, d: Path) -> Run:
    def add(root):
        root.create_array("data/label", data=np.array(["a", "b", "c", "d"], dtype="<U1"))
    return _new_from(i, d, _zarr_input(d, add), "--fps", 10)


def _zarr_pickle(i: Inputs, d: Path) -> Run:
    def add(root):
        root.create_array("data/obs", data=np.zeros((4, 1), np.float32))
    path = _zarr_input(d, add)
    _pickle_codec("data/obs/.zarray")(path)
    return _new_from(i, d, path, "--fps", 10)


def _unreadable_bag_file(i: Inputs, d: Path) -> Run:
    bag = d / "bag"
    shutil.copytree(i.bag, bag)
    for p in bag.iterdir():
        if p.suffix == ".mcap":
            p.chmod(0)
    s = i.store(d, ros=True)
    return Run(["ingest", bag, "--map", Inputs.map(d, MAP), "--out", s], s, no_dac=True)


def _huge_images(i: Inputs, d: Path) -> Run:
    bag = write_bag(d / "cams", n_joint=50, n_images=50)
    m = Inputs.map(d, MAP + "  observation.images.cam: {topic: /cam, image_size: [16000, 16000]}\n")
    return Run(["ingest", bag, "--map", m, "--out", d / "new.zarr"], d / "new.zarr")


def _kill_then(point: str) -> Callable[[Inputs, Path], list[Run]]:
    def before(i: Inputs, d: Path) -> list[Run]:
        s = d / "store.zarr"
        return [Run(["ingest", i.b, "--out", s], s, env={"SEFA_FAULT": point})]
    return before


def _after_kill(args_of: Callable[[Inputs, Path], list]) -> Callable[[Inputs, Path], Run]:
    def make(i: Inputs, d: Path) -> Run:
        s = d / "store.zarr"  # left by the killed run of `before`
        return Run(args_of(i, s), s)
    return make


CASES: list[Case] = [
    # 1: crashes
    Case("kill -9 while the commit deletes its journal, then ingest the same file again",
         "1 crash", "h5py", _after_kill(lambda i, s: ["ingest", i.b, "--out", s]),
         exit=0, fragments=("already in",), store="as after the append",
         before=_kill_then("commit.deleting")),
    Case("kill -9 after the data is written (before the commit), then inspect (prints the "
         "store: 2 episodes)",
         "1 crash", "h5py", _after_kill(lambda i, s: ["inspect", s]), exit=0,
         fragments=("2 episodes",), store="as before the append",
         before=_kill_then("append.attrs")),
    # 2: integrity
    Case("a deleted image chunk, then ingest", "2 integrity", "h5py",
         lambda i, d: _ingest_b(i, d, _rm("data/observation.cam_image/3.0.0.0")),
         fragments=("chunk 3.0.0.0 is missing", "would read it as zeros")),
    Case("a deleted meta/episode_ends, then ingest", "2 integrity", "h5py",
         lambda i, d: _ingest_b(i, d, _rm("meta/episode_ends")),
         fragments=("meta/episode_ends", "missing")),
    Case("a truncated chunk, then inspect", "2 integrity", "h5py",
         lambda i, d: _inspect(i, d, _truncate("data/action/0.0", 10)),
         fragments=("data/action", "chunk 0.0 is 10 bytes")),
    Case("one flipped byte in an image chunk, plain inspect (sizes only for images)",
         "2 integrity", "h5py",
         lambda i, d: _inspect(i, d, _flip_byte("data/observation.cam_image/5.0.0.0")), exit=0),
    Case("one flipped byte in an image chunk, inspect --verify", "2 integrity", "h5py",
         lambda i, d: _inspect(i, d, _flip_byte("data/observation.cam_image/5.0.0.0"),
                               "--verify"), fragments=("does not match its checksum",)),
    Case("broken attributes: .zattrs is not JSON", "2 integrity", "h5py",
         lambda i, d: _inspect(i, d, _attrs(None, "{garbage")), fragments=(".zattrs",
                                                                           "not valid JSON")),
    Case("broken attributes: fps is a string", "2 integrity", "h5py",
         lambda i, d: _inspect(i, d, _attrs(lambda a: a.update(fps="ten"))),
         fragments=("fps", "broken store attributes")),
    Case("a garbage journal, then ingest", "2 integrity", "h5py",
         lambda i, d: _ingest_b(i, d, _garbage_journal), fragments=("journal", "damaged")),
    Case("a pickle codec in a store array, then inspect", "2 integrity", "h5py",
         lambda i, d: _inspect(i, d, _pickle_codec("data/action/.zarray")),
         fragments=("pickle",)),
    Case("a read-only store, then ingest", "4 one line", "h5py",
         lambda i, d: Run(*_ro(i, d)), fragments=("read-only",)),
    # 3: no silent data loss
    Case("HDF5: an observation longer than the actions in one demo", "3 data loss", "h5py",
         lambda i, d: _new_from(i, d, write_demos(d / "x.hdf5", state_rows=20), "--fps", 10),
         fragments=("data/demo_1/obs/state", "20 rows for 9 actions"), store="not created"),
    Case("the same with --skip-bad-demos", "3 data loss", "h5py",
         lambda i, d: _new_from(i, d, write_demos(d / "x.hdf5", state_rows=20), "--fps", 10,
                                "--skip-bad-demos"),
         exit=0, fragments=("warning: ", "skipped demo demo_1 (--skip-bad-demos)"),
         store="written"),
    Case("HDF5: a `total` attribute that disagrees", "3 data loss", "h5py",
         lambda i, d: _new_from(i, d, write_demos(d / "x.hdf5", total=99), "--fps", 10,
                                "--dry-run"),
         exit=0, fragments=("warning: ", "data.attrs['total'] is 99 but the demos hold 15"),
         store="not created"),
    # 4: one clear line
    Case("HDF5: scalar actions", "4 one line", "h5py",
         lambda i, d: _new_from(i, d, write_demos(d / "x.hdf5", actions=np.float64(1.0)),
                                "--fps", 10),
         fragments=("actions must be numbers", "single float64 value"), store="not created"),
    Case("HDF5: string actions", "4 one line", "h5py",
         lambda i, d: _new_from(i, d, write_demos(d / "x.hdf5", actions=np.array(
             [b"left"] * 6)), "--fps", 10), fragments=("actions must be numbers",),
         store="not created"),
    Case("Zarr input: a string array under data/", "4 one line", "zarr",
         _zarr_strings, fragments=("data/label", "numbers"), store="not created"),
    Case("Zarr input: a pickle codec (never unpickled)", "4 one line", "zarr",
         _zarr_pickle, fragments=("pickle", "data/obs/.zarray"), store="not created"),
    *[Case(f"--fps {v}", "4 one line", "h5py",
           lambda i, d, v=v: _new_from(i, d, i.a, "--fps", v),
           fragments=("--fps", "frame rate"), store="not created")
      for v in ("nan", "inf", "1e12", "0", "-5")],
    Case("map: fps .nan", "4 one line", "rosbags",
         _bag_map(MAP.replace("fps: 10", "fps: .nan")), fragments=("fps", "frame rate"),
         store="not created"),
    Case("map: image_size [100000, 100000]", "4 one line", "rosbags",
         _bag_map(MAP + "  img: {topic: /joint_states, image_size: [100000, 100000]}\n"),
         fragments=("image_size",), store="not created"),
    Case("map: image_size [16000, 16000] for 50 images (memory estimate)", "4 one line",
         "rosbags", _huge_images, fragments=("needs about", "memory", "smaller image_size"),
         store="not created"),
    Case("map: unknown dtype", "4 one line", "rosbags",
         _bag_map(MAP.replace("field: position}", "field: position, dtype: float99}")),
         fragments=("dtype", "float99"), store="not created"),
    Case("map: the path is a directory", "4 one line", "rosbags",
         lambda i, d: Run(["ingest", i.bag, "--map", d, "--out", d / "new.zarr"],
                          d / "new.zarr"), fragments=("is a directory",), store="not created"),
    *[Case(f"map: feature key {k!r}", "4 one line", "rosbags",
           _bag_map(f"fps: 10\nfeatures:\n  {json.dumps(k)}: {{topic: /joint_states, "
                    "field: position}\n"), fragments=("dataset key",), store="not created")
      for k in ("", "a/b", "../x")],
    Case("an EIO error while reading an HDF5 dataset", "4 one line", "h5py",
         lambda i, d: Run(["ingest", i.b, "--out", i.store(d)], d / "store.zarr",
                          patch=EIO_PATCH), fragments=("Input/output error",)),
    Case("an unreadable file inside a bag directory", "4 one line", "rosbags",
         _unreadable_bag_file, fragments=("Permission denied",)),
    Case("--skip-failed: an input failing with EIO, then a good one", "4 one line",
         "h5py, zarr",
         lambda i, d: Run(["ingest", i.b, _zarr_input(d, lambda root: None), "--out",
                           d / "new.zarr", "--fps", 10, "--skip-failed"], d / "new.zarr",
                          patch=EIO_PATCH),
         fragments=("Input/output error",), store="written"),
    Case("--json: a failure prints a JSON error object on stdout", "4 one line", "h5py",
         lambda i, d: _new_from(i, d, i.a, "--fps", "nan", "--json"),
         fragments=("--fps",), store="not created"),
    # 6: maps that cannot mean what they say
    Case("map: a feature key given twice", "6 maps", "rosbags",
         _bag_map(MAP + "  observation.state: {topic: /joint_states, field: velocity}\n"),
         fragments=("appears twice",), store="not created"),
    Case("map: float joint angles cast to uint8", "6 maps", "rosbags",
         _bag_map(MAP.replace("field: position}", "field: position, dtype: uint8}")),
         fragments=("uint8", "allow_lossy_cast"), store="not created"),
    Case("map: negative gap_s", "6 maps", "rosbags",
         _bag_map(MAP + "split: {gap_s: -1}\n"), fragments=("gap_s", "positive"),
         store="not created"),
    Case("map: min_length 0", "6 maps", "rosbags",
         _bag_map(MAP + "min_length: 0\n"), fragments=("min_length",), store="not created"),
]


def _ro(i: Inputs, d: Path) -> tuple:
    s = i.store(d)
    _read_only(s)
    return ["ingest", i.b, "--out", s], s, {}, "", True


def _handover_case() -> Case | None:
    path = SHARED / "robosuite141_two_arm_handover_7demos.hdf5"
    if not path.exists():
        return None
    return Case("HDF5: per-demo logs at their own rate (skipped keys are printed)",
                "3 data loss", "shared data (handover)",
                lambda i, d: _new_from(i, d, path, "--dry-run"), exit=0,
                fragments=("warning: ", "skipped key controller_info/counters: 1380 rows for "
                           "641 actions in demo_0"), store="not created")


# --------------------------------------------------------------------------- running

def _drop_dac() -> None:
    """Run the child without CAP_DAC_OVERRIDE / CAP_DAC_READ_SEARCH, so that file modes bind
    even for root (a CI container runs as root)."""
    if os.geteuid() != 0:
        return
    libc = ctypes.CDLL(None, use_errno=True)
    for cap in (1, 2):
        if libc.prctl(24, cap, 0, 0, 0) != 0:  # PR_CAPBSET_DROP
            raise OSError(ctypes.get_errno(), "prctl(PR_CAPBSET_DROP)")


def snapshot(path: Path) -> dict[str, bytes] | None:
    if not path.exists():
        return None
    out = {}
    for p in sorted(path.rglob("*")):
        if p.is_file():
            try:
                out[str(p.relative_to(path))] = p.read_bytes()
            except PermissionError:
                out[str(p.relative_to(path))] = b"<unreadable>"
    return out


def _child(run: Run) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-c", _RUNNER.format(patch=run.patch)] if run.patch \
        else [sys.executable, "-m", "sefa_cli.main"]
    env = {**os.environ, "PYTHONPATH": str(REPO), **run.env}
    env.pop("SEFA_FAULT", None) if "SEFA_FAULT" not in run.env else None
    return subprocess.run(cmd + [str(a) for a in run.args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=300,
                          preexec_fn=_drop_dac if run.no_dac else None)


def run_case(case: Case, inputs: Inputs, work: Path) -> Result:
    work.mkdir(parents=True, exist_ok=True)
    for pre in (case.before(inputs, work) if case.before else []):
        s = pre.watch
        if not s.exists():
            shutil.copytree(inputs.base, s)
        r = _child(pre)
        assert r.returncode == -signal.SIGKILL, (case.name, r.returncode, r.stderr[-1000:])
    run = case.make(inputs, work)
    before = snapshot(run.watch)
    r = _child(run)
    after = snapshot(run.watch)
    if case.before is not None:  # a recovery: which whole state the store reads as
        store = next((f"as {n} the append" for n in ("before", "after")
                      if after == inputs.state(n)), "neither state")
    elif before == after:
        store = "unchanged" if before is not None else "not created"
    else:
        store = "written" if before is None else "changed"
    lines = [ln for ln in r.stderr.strip().splitlines() if ln.strip()]
    error = [ln for ln in lines if ln.startswith("error: ")]
    warning = [ln for ln in lines if ln.startswith("warning: ")]
    out = [ln for ln in r.stdout.splitlines() if ln.strip()]
    # the line that matters: the error, else the first warning, else the last report line
    line = (error[-1] if error else warning[0] if warning else lines[-1] if lines
            else out[0] if out else "")
    return Result(case, r.returncode, line, r.stderr, r.stdout, store)


def all_cases() -> list[Case]:
    from lerobot_faults import lerobot_cases  # 7: LeRobot datasets (made from shared data)

    extra = _handover_case()
    return CASES + ([extra] if extra else []) + lerobot_cases(SHARED)


def can_drop_dac() -> bool:
    try:
        r = subprocess.run([sys.executable, "-c", "pass"], preexec_fn=_drop_dac, timeout=60)
        return r.returncode == 0
    except (OSError, subprocess.SubprocessError):
        return False


def make_inputs(root: Path | None = None) -> Inputs:
    return Inputs(Path(root or tempfile.mkdtemp(prefix="sefa-bad-")))


__all__ = ["CASES", "Case", "Inputs", "Result", "all_cases", "can_drop_dac", "make_inputs",
           "run_case", "snapshot"]
