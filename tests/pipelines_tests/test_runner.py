"""The cached stage runner: caching, invalidation, atomic artifacts, crash recovery, the lock.

Toy stages write small files; every stage function counts its calls so that a test can say
exactly which stages ran.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from collections import Counter
from pathlib import Path
from typing import Callable

import pytest

from sefa_pipelines import runner
from sefa_pipelines.runner import (Stage, Workspace, canonical_json, pipeline_status, run_pipeline,
                              run_stage)
from sefa_data.errors import SefaInputError

REPO = Path(__file__).resolve().parents[2]


# --- a toy three-stage chain: data.txt -> a -> b -> c/iter_1 -------------------------------------

class Chain:
    def __init__(self, tmp_path: Path):
        self.ws = Workspace(tmp_path / "ws")
        self.data = tmp_path / "data.txt"
        self.data.write_text("1 2 3")
        self.configs = {"a": {"a": {"scale": 1}}, "b": {"b": {"offset": 0}},
                        "c": {"align": {"eps": 0.05, "metric": "l2"}}}
        self.calls: Counter[str] = Counter()
        self.logs: list[str] = []
        self.fail: dict[str, BaseException] = {}

    def stages(self) -> list[Stage]:
        return [
            Stage("a", "a", self.configs["a"], [str(self.data)], self._fn("a", self._a)),
            Stage("b", "b", self.configs["b"], ["a"], self._fn("b", self._b)),
            Stage("c", "c/iter_1", self.configs["c"], ["b"], self._fn("c", self._c)),
        ]

    def stage(self, name: str) -> Stage:
        return next(s for s in self.stages() if s.name == name)

    def run(self, force: tuple[str, ...] = ()) -> set[str]:
        """Run the pipeline; the names of the stages that actually ran."""
        before = Counter(self.calls)
        run_pipeline(self.ws, self.stages(), force=set(force), log=self.logs.append)
        return {name for name in self.calls if self.calls[name] > before[name]}

    def status(self) -> dict[str, tuple[str, str]]:
        return {name: (state, reason) for name, state, reason
                in pipeline_status(self.ws, self.stages())}

    def _fn(self, name: str, body: Callable[[Path], dict]) -> Callable[[Path], dict]:
        def run(out: Path) -> dict:
            self.calls[name] += 1
            summary = body(out)
            if name in self.fail:
                (out / "half_written.bin").write_bytes(b"\0" * 100)
                raise self.fail[name]
            return summary
        return run

    def _a(self, out: Path) -> dict:
        scale = self.configs["a"]["a"]["scale"]
        values = [int(v) * scale for v in self.data.read_text().split()]
        (out / "values.json").write_text(json.dumps(values))
        return {"n": len(values)}

    def _b(self, out: Path) -> dict:
        values = json.loads((self.ws.root / "a" / "values.json").read_text())
        offset = self.configs["b"]["b"]["offset"]
        (out / "values.json").write_text(json.dumps([v + offset for v in values]))
        return {"sum": sum(values) + offset * len(values)}

    def _c(self, out: Path) -> dict:
        (out / "sub").mkdir()
        (out / "sub" / "copy.json").write_bytes((self.ws.root / "b" / "values.json").read_bytes())
        return {"eps": self.configs["c"]["align"]["eps"]}


@pytest.fixture
def chain(tmp_path: Path) -> Chain:
    return Chain(tmp_path)


def snapshot(directory: Path) -> dict[str, bytes]:
    return {p.relative_to(directory).as_posix(): p.read_bytes()
            for p in sorted(directory.rglob("*")) if p.is_file()}


def leftovers(root: Path) -> list[Path]:
    return [p for p in root.rglob(".*")
            if ".tmp-" in p.name or ".old-" in p.name or p.name.endswith(".partial")]


# --- caching and invalidation --------------------------------------------------------------------

def test_first_run_runs_everything_second_run_nothing(chain: Chain):
    assert chain.run() == {"a", "b", "c"}
    chain.logs.clear()
    assert chain.run() == set()
    runs = {a: os.path.realpath(chain.ws.root / a) for a in ("a", "b", "c/iter_1")}
    assert chain.logs == [f"{n}: cached ({a} -> {Path(runs[a]).relative_to(chain.ws.root)})"
                          for n, a in (("a", "a"), ("b", "b"), ("c", "c/iter_1"))]
    assert all(Path(r).parent == chain.ws.root / "runs" / a for a, r in runs.items())
    assert (chain.ws.root / "c" / "iter_1" / "manifest.json").is_file()  # nested artifact path
    assert leftovers(chain.ws.root) == []


def test_changing_last_config_reruns_only_last(chain: Chain):
    chain.run()
    chain.configs["c"]["align"]["eps"] = 0.1
    assert chain.run() == {"c"}


def test_changing_first_config_reruns_the_whole_chain(chain: Chain):
    chain.run()
    chain.configs["a"]["a"]["scale"] = 2
    assert chain.run() == {"a", "b", "c"}
    assert json.loads((chain.ws.root / "b" / "values.json").read_text()) == [2, 4, 6]


def test_changing_an_input_file_reruns_from_its_reader(chain: Chain):
    chain.run()
    chain.data.write_text("4 5 6")  # same size, so only the content can tell
    assert chain.run() == {"a", "b", "c"}


def test_touching_an_input_without_changing_it_reruns_nothing(chain: Chain):
    chain.run()
    st = chain.data.stat()
    os.utime(chain.data, ns=(st.st_atime_ns, st.st_mtime_ns + 5_000_000_000))
    assert chain.run() == set()


def test_force_reruns_that_stage_and_downstream(chain: Chain):
    chain.run()
    assert chain.run(force=("b",)) == {"b", "c"}
    assert chain.run(force=("c",)) == {"c"}


def test_package_versions_are_recorded_but_not_part_of_the_key(chain: Chain, monkeypatch):
    chain.run()
    manifest = json.loads((chain.ws.root / "a" / "manifest.json").read_text())
    assert {"python", "numpy"} <= set(manifest["versions"])
    monkeypatch.setattr(runner, "package_versions", lambda: {"python": "9.9", "numpy": "99"})
    assert chain.run() == set()


def test_manifest_contents(chain: Chain):
    chain.run()
    a = json.loads((chain.ws.root / "a" / "manifest.json").read_text())
    b_manifest = (chain.ws.root / "b" / "manifest.json").read_text()
    b = json.loads(b_manifest)
    assert a["stage"] == "a" and a["artifact"] == "a" and a["status"] == "complete"
    assert a["config"] == {"a": {"scale": 1}}
    assert a["config_hash"] == hashlib.sha256(canonical_json(a["config"]).encode()).hexdigest()
    assert a["inputs"] == {str(chain.data): hashlib.sha256(b"1 2 3").hexdigest()}
    assert a["summary"] == {"n": 3}
    assert len(a["build_id"]) == 32 and a["build_id"] != b["build_id"]
    assert a["run_id"] == Path(os.path.realpath(chain.ws.root / "a")).name  # its folder's id
    assert a["duration_s"] >= 0 and a["created"].endswith("+00:00")
    # A downstream input is keyed on the upstream manifest's bytes.
    a_bytes = (chain.ws.root / "a" / "manifest.json").read_bytes()
    assert b["inputs"] == {"a": hashlib.sha256(a_bytes).hexdigest()}


def test_config_key_order_and_tuples_do_not_matter(chain: Chain):
    chain.configs["b"]["b"]["dims"] = [1, 2]
    chain.run()
    chain.configs["c"] = {"align": {"metric": "l2", "eps": 0.05}}
    chain.configs["b"] = {"b": {"dims": (1, 2), "offset": 0}}
    assert chain.run() == set()


# --- input files and the hash cache --------------------------------------------------------------

def test_unchanged_old_files_are_not_rehashed(tmp_path: Path, monkeypatch):
    ws = Workspace(tmp_path / "ws")
    store = tmp_path / "store"
    (store / "chunks").mkdir(parents=True)
    for i in range(3):
        (store / "chunks" / f"{i}").write_bytes(bytes([i]) * 10)
    old = time.time_ns() - 60_000_000_000
    for f in (store / "chunks").iterdir():
        os.utime(f, ns=(old, old))
    stage = Stage("s", "s", {}, [str(store)], lambda out: {})
    run_stage(ws, stage, log=lambda m: None)
    assert len(json.loads((ws.root / ".sefa" / "file_hashes.json").read_text())) == 3

    hashed: list[Path] = []
    real = runner._hash_file_contents
    monkeypatch.setattr(runner, "_hash_file_contents", lambda p: hashed.append(p) or real(p))
    assert ws.status(stage).state == "cached"
    assert hashed == []  # stat only

    os.utime(store / "chunks" / "1", ns=(old + 10**9, old + 10**9))
    assert ws.status(stage).state == "cached"  # touched: rehashed, same digest
    assert hashed == [store / "chunks" / "1"]

    (store / "chunks" / "2").write_bytes(b"changed")
    assert ws.status(stage) == runner.StageStatus("stale", f"input {store} changed")
    (store / "chunks" / "2").write_bytes(bytes([2]) * 10)
    assert ws.status(stage).state == "cached"
    (store / "chunks" / "new").write_bytes(b"")
    assert ws.status(stage).state == "stale"  # a new file changes a directory's fingerprint


def test_freshly_written_files_are_not_cached(tmp_path: Path):
    # Within a coarse mtime tick a rewrite can keep size and mtime; do not trust such entries.
    ws = Workspace(tmp_path / "ws")
    data = tmp_path / "fresh.txt"
    data.write_text("x")
    run_stage(ws, Stage("s", "s", {}, [str(data)], lambda out: {}), log=lambda m: None)
    cache = ws.root / ".sefa" / "file_hashes.json"
    assert not cache.exists() or str(data) not in json.loads(cache.read_text())


# --- status --------------------------------------------------------------------------------------

def test_status_reasons(chain: Chain):
    assert chain.status() == {
        "a": ("missing", "no complete artifact at a/"),
        "b": ("missing", "no complete artifact at b/"),
        "c": ("missing", "no complete artifact at c/iter_1/"),
    }
    chain.run()
    assert {name: s for name, (s, _) in chain.status().items()} == dict.fromkeys("abc", "cached")

    chain.configs["c"]["align"]["eps"] = 0.1
    assert chain.status()["c"] == ("stale", "config changed: align.eps 0.05 -> 0.1")
    chain.configs["c"]["align"]["eps"] = 0.05
    chain.configs["c"]["align"]["solver"] = "euler:1"
    assert chain.status()["c"] == ("stale", 'config changed: align.solver added ("euler:1")')
    del chain.configs["c"]["align"]["solver"], chain.configs["c"]["align"]["metric"]
    assert chain.status()["c"] == ("stale", 'config changed: align.metric removed (was "l2")')
    chain.configs["c"]["align"]["metric"] = "l2"

    # Upstream stale: downstream is reported stale too, since it will rerun.
    chain.configs["a"]["a"]["scale"] = 3
    assert chain.status() == {
        "a": ("stale", "config changed: a.scale 1 -> 3"),
        "b": ("stale", "upstream a will rerun"),
        "c": ("stale", "upstream b will rerun"),
    }
    chain.configs["a"]["a"]["scale"] = 1
    chain.data.write_text("7 8 9")
    assert chain.status()["a"] == ("stale", f"input {chain.data} changed")

    # After a rerun of a alone, b's own status names the upstream whose manifest changed.
    run_stage(chain.ws, chain.stage("a"), log=chain.logs.append)
    assert chain.ws.status(chain.stage("b")) == runner.StageStatus("stale", "input a changed")


def test_incomplete_artifacts_count_as_missing(chain: Chain):
    chain.run()
    manifest = chain.ws.root / "b" / "manifest.json"
    partial = json.loads(manifest.read_text()) | {"status": "partial"}
    manifest.write_text(json.dumps(partial))
    assert chain.status()["b"] == ("missing", "no complete artifact at b/")
    manifest.unlink()
    assert chain.status()["b"] == ("missing", "no complete artifact at b/")
    manifest.write_text("{ truncated")
    assert chain.status()["b"][0] == "missing"
    assert chain.run() == {"b", "c"}


def test_missing_upstream(chain: Chain):
    with pytest.raises(SefaInputError, match="input a is missing"):
        run_stage(chain.ws, chain.stage("b"), log=chain.logs.append)
    chain.run()
    (chain.ws.root / "a" / "manifest.json").unlink()
    assert chain.ws.status(chain.stage("b")) == runner.StageStatus("stale", "input a is missing")
    chain.data.unlink()
    with pytest.raises(SefaInputError, match=f"input {chain.data} is missing"):
        chain.run()


def test_bad_artifact_names_are_rejected():
    for bad in ("", "/abs", "../up", ".sefa", "reflow/.hidden"):
        with pytest.raises(ValueError):
            Stage("x", bad, {}, [], lambda out: {})


# --- failures leave the previous artifact alone --------------------------------------------------

@pytest.mark.parametrize("error", [RuntimeError("boom"), KeyboardInterrupt()])
def test_failure_keeps_previous_artifact(chain: Chain, error: BaseException):
    chain.run()
    before = snapshot(chain.ws.root / "c" / "iter_1")
    chain.configs["c"]["align"]["eps"] = 0.2
    chain.fail["c"] = error
    with pytest.raises(type(error)):
        chain.run()
    assert snapshot(chain.ws.root / "c" / "iter_1") == before
    assert leftovers(chain.ws.root) == []
    assert chain.status()["c"] == ("stale", "config changed: align.eps 0.05 -> 0.2")

    del chain.fail["c"]
    assert chain.run() == {"c"}


def test_interrupt_in_the_middle_keeps_upstream(chain: Chain):
    chain.run()
    before = snapshot(chain.ws.root / "b")
    chain.configs["b"]["b"]["offset"] = 1
    chain.fail["b"] = KeyboardInterrupt()
    with pytest.raises(KeyboardInterrupt):
        chain.run()
    assert snapshot(chain.ws.root / "b") == before
    del chain.fail["b"]
    assert chain.run() == {"b", "c"}  # c follows because b's manifest changed


def test_death_between_the_two_renames_is_repaired(chain: Chain):
    chain.run()
    root = chain.ws.root
    before = snapshot(root / "b")
    # What a SIGKILL between "final -> .old" and "tmp -> final" leaves behind.
    (root / "b").rename(root / ".b.old-999")
    (root / ".b.tmp-999").mkdir()
    (root / ".b.tmp-999" / "values.json").write_text("[]")
    assert chain.status()["b"][0] == "missing"
    assert chain.run() == set()  # the previous b is put back and is still valid
    assert snapshot(root / "b") == before
    assert leftovers(root) == []


# --- real processes: SIGKILL and the lock --------------------------------------------------------

SLOW_STAGE = textwrap.dedent("""
    import sys, time
    from pathlib import Path
    from sefa_pipelines.runner import Stage, Workspace, run_stage
    root, marker, version = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
    def slow(out):
        (out / "weights.bin").write_bytes(b"new" * 1000)
        marker.write_text("writing")
        time.sleep(60)
        return {}
    run_stage(Workspace(root), Stage("s", "s", {"v": version}, [], slow), log=lambda m: None)
""")


def start_slow_stage(root: Path, tmp_path: Path, version: str) -> subprocess.Popen:
    """A subprocess inside a stage (holding the lock) that has started writing its output."""
    marker = tmp_path / f"marker-{version}"
    child = subprocess.Popen([sys.executable, "-c", SLOW_STAGE, str(root), str(marker), version],
                             cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})
    deadline = time.monotonic() + 30
    while not marker.exists():
        assert child.poll() is None, "the slow stage exited early"
        assert time.monotonic() < deadline, "the slow stage never started"
        time.sleep(0.02)
    return child


def kill(child: subprocess.Popen) -> None:
    os.kill(child.pid, signal.SIGKILL)
    child.wait(timeout=10)


def quick_stage(version: str) -> Stage:
    def write(out: Path) -> dict:
        (out / "weights.bin").write_bytes(version.encode() * 1000)
        return {}
    return Stage("s", "s", {"v": version}, [], write)


@pytest.mark.parametrize("had_previous", [False, True])
def test_sigkill_mid_write(tmp_path: Path, had_previous: bool):
    ws = Workspace(tmp_path / "ws")
    if had_previous:
        run_stage(ws, quick_stage("old"), log=lambda m: None)
        before = snapshot(ws.root / "s")
    child = start_slow_stage(ws.root, tmp_path, "new")
    kill(child)

    partials = list((ws.root / "runs" / "s").glob(".*.partial"))
    assert len(partials) == 1 and (partials[0] / "weights.bin").exists()  # killed mid-write
    if had_previous:
        assert snapshot(ws.root / "s") == before
        assert ws.status(quick_stage("old")).state == "cached"
    else:
        assert not (ws.root / "s").exists()
        assert ws.status(quick_stage("new")).state == "missing"

    logs: list[str] = []
    ran, manifest = run_stage(ws, quick_stage("new"), log=logs.append)
    assert ran and manifest["config"] == {"v": "new"}
    assert f"s: removed {partials[0].name} left by an interrupted run" in logs
    assert leftovers(ws.root) == []
    assert ws.status(quick_stage("new")).state == "cached"


def test_lock_held_by_another_process(tmp_path: Path):
    ws = Workspace(tmp_path / "ws")
    child = start_slow_stage(ws.root, tmp_path, "v")
    try:
        with pytest.raises(SefaInputError,
                           match=rf"another sefa run holds the workspace lock \(pid {child.pid}\)"):
            run_pipeline(ws, [quick_stage("v")], log=lambda m: None)
    finally:
        kill(child)
    # The kernel released the lock with the dead process; no stale lock file to delete.
    run_pipeline(ws, [quick_stage("v")], log=lambda m: None)
    assert ws.status(quick_stage("v")).state == "cached"


def test_second_process_gets_a_clear_error(tmp_path: Path):
    ws = Workspace(tmp_path / "ws")
    script = textwrap.dedent("""
        import sys
        from pathlib import Path
        from sefa_pipelines.runner import Stage, Workspace, run_pipeline
        from sefa_data.errors import SefaInputError
        try:
            run_pipeline(Workspace(Path(sys.argv[1])),
                         [Stage("s", "s", {}, [], lambda out: {})], log=print)
        except SefaInputError as exc:
            print(exc)
            sys.exit(3)
    """)
    with ws.lock():
        with ws.lock():  # re-entrant within one Workspace: run_pipeline relies on it
            pass
        done = subprocess.run([sys.executable, "-c", script, str(ws.root)], cwd=REPO,
                              env={**os.environ, "PYTHONPATH": str(REPO)},
                              capture_output=True, text=True, timeout=30)
    assert done.returncode == 3, done.stderr
    assert f"another sefa run holds the workspace lock (pid {os.getpid()})" in done.stdout
    assert not (ws.root / "s").exists()
    # Released on exit, including after an error inside the block.
    with pytest.raises(RuntimeError):
        with ws.lock():
            raise RuntimeError
    with ws.lock():
        pass


# --- runs are kept, resumable, and relative to the workspace (issue 15) --------------------------

def test_an_old_run_survives_a_new_one_and_switching_back_is_free(chain: Chain):
    chain.run()
    first = {a: os.path.realpath(chain.ws.root / a) for a in ("a", "b", "c/iter_1")}
    kept = snapshot(Path(first["a"]))
    chain.configs["a"]["a"]["scale"] = 2
    assert chain.run() == {"a", "b", "c"}
    # a new config is a new run folder beside the old one, which is untouched
    assert os.path.realpath(chain.ws.root / "a") != first["a"]
    assert snapshot(Path(first["a"])) == kept
    assert len(list((chain.ws.root / "runs" / "a").iterdir())) == 2
    chain.configs["a"]["a"]["scale"] = 1
    chain.logs.clear()
    assert chain.run() == set()  # every stage finds its kept run of these settings
    assert {a: os.path.realpath(chain.ws.root / a) for a in first} == first
    assert "a: cached (a -> runs/a/" in chain.logs[0] and "a kept run; now current" in chain.logs[0]
    # --force rebuilds the run of the same key and leaves the other config's run alone
    assert chain.run(force=("a",)) == {"a", "b", "c"}
    assert len(list((chain.ws.root / "runs" / "a").iterdir())) == 2


def test_a_copied_workspace_is_fully_cached(tmp_path: Path):
    import shutil

    chain = Chain(tmp_path)
    chain.data = chain.ws.root / "data.txt"  # an input inside the workspace, like dataset.zarr
    chain.ws.root.mkdir(parents=True)
    chain.data.write_text("4 5 6")
    chain.run()
    manifest = json.loads((chain.ws.root / "a" / "manifest.json").read_text())
    assert list(manifest["inputs"]) == ["./data.txt"]
    assert str(chain.ws.root) not in json.dumps(manifest)
    copy = tmp_path / "elsewhere" / "ws"
    shutil.copytree(chain.ws.root, copy, symlinks=True)
    moved = Chain(tmp_path / "elsewhere")
    moved.ws, moved.data = Workspace(copy), copy / "data.txt"
    assert {n: s for n, (s, _) in moved.status().items()} == {"a": "cached", "b": "cached",
                                                             "c": "cached"}
    assert moved.run() == set()


def test_an_interrupted_training_stage_keeps_its_checkpoint_and_resumes(chain: Chain):
    """A stage whose build folder holds a training checkpoint when it is interrupted keeps it
    (not as a complete artifact); the next build of the same run id starts from it."""
    stage, seen, partial = interrupted_training(chain)
    logs = chain.logs
    assert chain.ws.status(stage).state == "missing"  # not a complete artifact
    ran, manifest = run_stage(chain.ws, stage, log=logs.append)
    assert ran and seen == [False, True] and manifest["summary"] == {"steps": 2}
    assert any("continuing the interrupted run" in line for line in logs)
    assert not partial.exists() and chain.ws.status(stage).state == "cached"


def test_a_training_stage_stopped_by_an_error_does_not_say_interrupted(chain: Chain):
    """The kept checkpoint's line says what happened: an error is not a Ctrl-C."""
    def train(out: Path) -> dict:
        fake_checkpoint(out / "checkpoints" / "latest")
        raise OSError(28, "No space left on device")

    stage = Stage("t", "t", {"steps": 2}, [], train)
    logs: list[str] = []
    with pytest.raises(OSError):
        run_stage(chain.ws, stage, log=logs.append)
    assert logs[-1].startswith("t: stopped by an error; its last checkpoint is kept: runs/t/.")
    assert "interrupted" not in logs[-1]


def fake_checkpoint(directory: Path) -> None:
    """What the runner checks of a checkpoint it would resume from (sefa_model/policy/checkpoint.py's
    open_checkpoint: config.json's sections and the checksums), without any weights."""
    from sefa_model.policy.checkpoint import REQUIRED_SECTIONS, write_checksums

    directory.mkdir(parents=True, exist_ok=True)
    (directory / "config.json").write_text(json.dumps(
        {"checkpoint_format": 1, "kind": "base_flow",
         "train_config": {name: {} for name in REQUIRED_SECTIONS}}))
    (directory / "model.safetensors").write_bytes(b"weights")
    write_checksums(directory)


def interrupted_training(chain: Chain) -> tuple[Stage, list[bool], Path]:
    """A training stage interrupted once with a checkpoint kept; (stage, seen, its partial):
    `seen` records, per build, whether it started from a checkpoint."""
    seen: list[bool] = []

    def train(out: Path) -> dict:
        seen.append((out / "checkpoints" / "latest" / "config.json").exists())
        fake_checkpoint(out / "checkpoints" / "latest")
        if len(seen) == 1:
            raise KeyboardInterrupt
        return {"steps": 2}

    stage = Stage("t", "t", {"steps": 2}, [], train)
    with pytest.raises(KeyboardInterrupt) as interrupt:
        run_stage(chain.ws, stage, log=chain.logs.append)
    partial = list((chain.ws.root / "runs" / "t").glob(".*.partial"))
    assert len(partial) == 1
    # the interrupt carries what was kept, for the line the command ends with
    assert interrupt.value.kept == runner.KeptRun(
        "t", partial[0].relative_to(chain.ws.root).as_posix())
    return stage, seen, partial[0]


def test_a_damaged_partial_run_is_named_and_force_starts_it_over(chain: Chain):
    """Issue 23: a kept checkpoint that fails its checks is never continued (and never
    "continued" forever): the same command names it; --force starts over."""
    stage, seen, partial = interrupted_training(chain)
    (partial / "checkpoints" / "latest" / "model.safetensors").write_bytes(b"weightz")
    for _ in range(2):  # the same error each time, nothing run
        with pytest.raises(SefaInputError, match=r"\.partial: the interrupted run here cannot be "
                                                 r"continued \(.*model.safetensors: checksum "
                                                 r"mismatch.*pass --force to start it over"):
            run_stage(chain.ws, stage, log=chain.logs.append)
    assert seen == [False]
    ran, manifest = run_stage(chain.ws, stage, force=True, log=chain.logs.append)
    assert ran and seen == [False, False] and manifest["summary"] == {"steps": 2}
    assert not partial.exists() and chain.ws.status(stage).state == "cached"


def test_a_partial_that_is_a_file_is_replaced(chain: Chain):
    stage, seen, partial = interrupted_training(chain)
    shutil.rmtree(partial)
    partial.write_text("not a folder")
    ran, _ = run_stage(chain.ws, stage, log=chain.logs.append)
    assert ran and seen == [False, False] and chain.ws.status(stage).state == "cached"
    assert any(f"removed {partial.name}" in line for line in chain.logs)


def test_summary_paths_are_relative_to_the_workspace(chain: Chain):
    def write(out: Path) -> dict:
        (out / "x.zarr").mkdir()
        return {"path": str(out / "x.zarr"), "input": str(chain.ws.root / "a" / "values.json")}

    chain.run()
    _, manifest = run_stage(chain.ws, Stage("w", "w", {}, ["a"], write), log=lambda m: None)
    run = os.path.realpath(chain.ws.root / "w")
    assert manifest["summary"] == {
        "path": Path(run).relative_to(chain.ws.root).as_posix() + "/x.zarr",
        "input": "./a/values.json"}


# --- the decision, one pure function for both the single-process and the torchrun path ----------

def test_decide_chooses_cached_kept_missing_or_build():
    from sefa_pipelines.runner import StageStatus, decide

    ok, stale = StageStatus("cached", "up to date"), StageStatus("stale", "config changed: x")
    fine, lacking = {"./data": "abc"}, {"./data": "abc", "a": None}
    kept = Path("runs/a/123")
    assert decide(ok, fine, False, None).action == "cached"
    assert decide(ok, fine, True, None) == runner.Decision("build", "forced")
    assert decide(stale, fine, False, kept) == runner.Decision("kept", stale.reason, kept)
    assert decide(stale, fine, True, kept).action == "build"  # --force rebuilds even a kept run
    assert decide(stale, fine, False, None) == runner.Decision("build", stale.reason)
    missing = decide(stale, lacking, False, None)
    assert missing.action == "missing" and missing.reason == "input a is missing (run its stage first)"


def test_a_ctrl_c_before_the_first_checkpoint_says_nothing_was_kept(chain: Chain):
    """A training stage interrupted before its first checkpoint keeps nothing (there is nothing
    to continue from); the command's last line says so, and why, where it said only that the
    stores were as they were."""
    from sefa_pipelines.workspace import _saying_what_was_kept

    def train(out: Path) -> dict:
        (out / "train_log.jsonl").write_text("{}\n")  # some steps ran, no checkpoint yet
        raise KeyboardInterrupt

    stage = Stage("train", "train", {"train": {"training": {"checkpoint_every": 500}}}, [], train)
    with pytest.raises(KeyboardInterrupt) as interrupt, _saying_what_was_kept("train", [stage]):
        run_stage(chain.ws, stage, log=chain.logs.append)
    assert interrupt.value.line == (
        "interrupted: train had not reached its first checkpoint (every 500 steps: "
        "training.checkpoint_every), so nothing of it was kept; `sefa train` starts it over "
        "(the finished stages before it are kept)")
    assert not list((chain.ws.root / "runs" / "train").glob(".*.partial"))
    couplings = Stage("reflow iter 1", "reflow/iter_1", {"couplings": {"samples_per_window": 3},
                                                         "reflowed_flow": None}, [], train)
    assert runner.lost_words(couplings).startswith("reflow iter 1 had finished no block")
    assert runner.lost_words(Stage("align", "align", {"eps": 0.1}, [], train)) is None
