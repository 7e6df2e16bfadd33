"""`sefa collect` into a file that is already there never loses a recorded demonstration: it
refuses, appends (--append) or replaces when told (--force); a bad request is refused before any
episode is recorded; a kill -9 or a Ctrl-C at each commit point leaves the old file or the new
one (sefa_sim/demo_file.py).

The files are written by the real collector: Meta-World's reach task and its scripted policy
(about a second per episode here, most of it building the env). The commands run in-process
(tests/sefa_inprocess.py), the faults in child processes (a kill -9 needs one).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

import sefa_sim  # noqa: F401  (sets MUJOCO_GL before mujoco loads)

h5py = pytest.importorskip("h5py")
try:
    import metaworld  # noqa: F401
except (ImportError, OSError) as e:  # OSError: mujoco's shared library fails to load
    pytest.skip(f"metaworld cannot be imported ({type(e).__name__}: {e}); "
                "install the sim extra: pip install -e '.[sim]'", allow_module_level=True)

from sefa_inprocess import sefa

REPO = Path(__file__).resolve().parents[2]
REACH = ["--env", "metaworld:reach"]


def demos(path: Path) -> dict[str, tuple[int, bytes, bytes]]:
    """{demo name: (its seed, its actions' bytes, its states' bytes)}."""
    with h5py.File(path, "r") as f:
        return {n: (int(g.attrs["seed"]), g["actions"][()].tobytes(), g["states"][()].tobytes())
                for n, g in f["data"].items()}


def one_error(r) -> str:
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 1 and len(lines) == 1 and lines[0].startswith("error: "), r.stderr
    assert "Traceback" not in r.stderr and "a bug in sefa" not in r.stderr
    return lines[0]


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    """Two demonstrations of reach, seeds 5 and 6."""
    path = tmp_path_factory.mktemp("collect") / "demos.hdf5"
    r = sefa("collect", path, *REACH, "--episodes", "2", "--seed", "5")
    assert "2/2 successful episodes kept" in r.stdout
    return path


def test_a_collect_into_an_existing_file_never_loses_a_demonstration(recorded, tmp_path) -> None:
    path = tmp_path / "demos.hdf5"
    path.write_bytes(recorded.read_bytes())
    before = path.read_bytes()
    # the issue's run: once replaced the file by seed 9's demonstration alone
    line = one_error(sefa("collect", path, *REACH, "--episodes", "1", "--seed", "9", ok=False))
    assert line == (f"error: {path}: already holds 2 demonstrations (seeds 5, 6): --append adds "
                    "the new ones after them, --force replaces the file")
    # once left a file without a demonstration
    line = one_error(sefa("collect", path, *REACH, "--episodes", "0", ok=False))
    assert line == "error: --episodes: 0 is too small (valid: an integer in [1, 1000000])"
    line = one_error(sefa("collect", path, *REACH, "--seed", "6", "--episodes", "1", "--append",
                          ok=False))
    assert "--seed: already holds the demonstration(s) of seed(s) 6" in line
    line = one_error(sefa("collect", path, "--env", "metaworld:push", "--seed", "9",
                          "--episodes", "1", "--append", ok=False))
    assert 'another environment (env_args.task: "reach" there, "push" now)' in line
    assert path.read_bytes() == before

    old = demos(path)
    r = sefa("collect", path, *REACH, "--episodes", "1", "--seed", "9", "--append")
    assert "appended after its 2, it holds 3" in r.stdout
    now = demos(path)
    assert {n: now[n] for n in old} == old  # the earlier demonstrations, byte for byte
    assert [s for s, _, _ in now.values()] == [5, 6, 9]
    with h5py.File(path, "r") as f:
        assert f["data"].attrs["total"] == sum(len(g["actions"]) for g in f["data"].values())
        train, valid = ([n.decode() for n in f[f"mask/{m}"][()]] for m in ("train", "valid"))
    with h5py.File(recorded, "r") as f:  # the earlier split kept, the new demo added to it
        assert [n.decode() for n in f["mask/valid"][()]] == valid
    assert sorted(train + valid) == ["demo_0", "demo_1", "demo_2"]

    sefa("collect", path, *REACH, "--episodes", "1", "--seed", "11", "--force")
    assert [s for s, _, _ in demos(path).values()] == [11]


def test_a_bad_request_is_refused_before_anything_is_recorded(tmp_path) -> None:
    (tmp_path / "afile").write_text("x")
    cases = [
        (["--seed", "-1"], "error: --seed: -1 is too small (valid: an integer in [0, 4294967295])"),
        (["--seed", "4294967295", "--episodes", "2"], "error: --seed: 4294967295 with 2 "
                                                      "episodes reaches seed 4294967296"),
        (["--episodes", "-3"], "error: --episodes: -3 is too small"),
        (["--append", "--force"], "error: --append: --append keeps the file's demonstrations "
                                  "and --force replaces them"),
    ]
    for extra, said in cases:
        line = one_error(sefa("collect", tmp_path / "d.hdf5", *REACH, *extra, ok=False))
        assert line.startswith(said), line
    # a folder at the output: once refused only after every episode was recorded
    r = sefa("collect", tmp_path, *REACH, "--episodes", "50", ok=False)
    assert one_error(r) == (f"error: {tmp_path}: is a directory; collect writes one HDF5 file "
                            "(give a file name, e.g. demos.hdf5)") and r.stdout == ""
    line = one_error(sefa("collect", tmp_path / "afile" / "d.hdf5", *REACH, ok=False))
    assert f"{tmp_path / 'afile'} is not a folder" in line
    (tmp_path / "junk.hdf5").write_text("not hdf5")
    line = one_error(sefa("collect", tmp_path / "junk.hdf5", *REACH, "--append", ok=False))
    assert "is not a readable HDF5 file" in line and "--force replaces it" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "junk.hdf5"]


def _child(args: list, fault: str | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    env.pop("SEFA_FAULT", None)
    if fault:
        env["SEFA_FAULT"] = fault
    return subprocess.run([sys.executable, "-m", "sefa_cli.main", *map(str, args)], env=env,
                          capture_output=True, text=True, timeout=300,
                          preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


@pytest.mark.parametrize("point", ["collect.written", "collect.published"])
def test_kill_and_ctrl_c_at_each_commit_point_leave_the_old_file_or_the_new_one(
        recorded, tmp_path, point) -> None:
    path = tmp_path / "demos.hdf5"
    path.write_bytes(recorded.read_bytes())
    before = path.read_bytes()
    append = ["collect", path, *REACH, "--episodes", "1", "--seed", "9", "--append"]
    published = point == "collect.published"

    r = _child(append, fault=point)  # kill -9
    assert r.returncode == -signal.SIGKILL
    if published:
        assert [s for s, _, _ in demos(path).values()] == [5, 6, 9]
        path.write_bytes(before)
    else:
        assert path.read_bytes() == before
        assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]  # its temporary

    r = _child(append, fault=f"{point}:sigint")  # Ctrl-C
    assert r.returncode == 130, r.stderr
    said = [ln for ln in r.stderr.splitlines() if ln.strip()][-1]
    if published:
        assert said == f"interrupted after {path} was written: it is complete"
        assert [s for s, _, _ in demos(path).values()] == [5, 6, 9]
        path.write_bytes(before)
    else:
        assert said == f"interrupted: {path} is as it was (1 episode(s) recorded are not in it)"
        assert path.read_bytes() == before
    # the killed run's temporary is gone once the next collect starts, which appends
    r = sefa(*append)
    assert [s for s, _, _ in demos(path).values()] == [5, 6, 9]
    assert [p.name for p in tmp_path.iterdir()] == ["demos.hdf5"]
