"""The frozen-features cache (issue 23) through the real `sefa distill`: a damaged entry (a
flipped bit, a missing tensor, the wrong width, NaN) stops the command with one line naming its
file and what is wrong, exit 1, and nothing published; `--force` encodes it again."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from safetensors.torch import load_file, save_file

from cli_inprocess import run_cli

REPO = Path(__file__).resolve().parents[2]
TINY = ["shape_meta.obs.keypoint.type=low_dim", "shape_meta.obs.state.dims=[0,2]",
        "policy.head=mlp", "policy.mlp_hidden_dims=[32,32]", "policy.time_embed_dim=16",
        "training.max_steps=20", "training.batch_size=32", "training.lr=1e-3",
        "training.lr_warmup_steps=5", "training.val_every=20", "training.checkpoint_every=20",
        "training.val_batches=1", "training.val_sample_windows=8", "training.log_every=10"]
STUDENT = ["training.max_steps=4", "training.checkpoint_every=4", "training.val_every=4",
           "training.log_every=2"]


def sefa(ws: Path, *args) -> subprocess.CompletedProcess:
    """`sefa ARGS -w WS` in-process through sefa_cli.main.main (tests/cli_inprocess.py), with the one
    torch thread its children had (the artifacts catalogue runs `distill` on a damaged entry in
    a real child: tests/artifact_bad_inputs.py)."""
    return run_cli(*args, "-w", ws, cwd=REPO, threads=1)


@pytest.fixture(scope="module")
def reflowed(shared_data, tmp_path_factory) -> Path:
    """A workspace whose reflow stage has written the features entry that distill reads."""
    ws = tmp_path_factory.mktemp("features")
    r = sefa(ws, "ingest", shared_data / "pusht_cchi_v7_replay.zarr", "--fps", "10",
             "--key", "keypoint", "--key", "state", "--key", "action")
    assert r.returncode == 0, r.stderr[-2000:]
    (ws / "sefa.yaml").write_text(yaml.safe_dump({
        "train": TINY, "reflow": {"samples_per_window": 2, "max_windows": 16},
        "distill": {"align": False, "train_overrides": STUDENT}}))
    r = sefa(ws, "reflow", "-y")
    assert r.returncode == 0, r.stderr[-2000:]
    return ws


@pytest.fixture
def ws(reflowed, tmp_path) -> Path:
    ws = tmp_path / "ws"
    shutil.copytree(reflowed, ws)
    return ws


def entry_file(ws: Path) -> Path:
    (entry,) = (ws / "features").iterdir()
    return entry / "features.safetensors"


def flip_a_bit(f: Path) -> None:
    data = bytearray(f.read_bytes())
    data[-5] ^= 0x04
    f.write_bytes(bytes(data))


def rewrite(f: Path, change) -> None:
    """A well-formed safetensors file with other content, its recorded checksum updated too, so
    that only the content checks can catch it."""
    import hashlib
    import json

    tensors = load_file(str(f))
    change(tensors)
    save_file(tensors, str(f))
    meta = json.loads((f.parent / "meta.json").read_text())
    meta["sha256"] = hashlib.sha256(f.read_bytes()).hexdigest()
    (f.parent / "meta.json").write_text(json.dumps(meta))


def nan(t):
    t["features"][3, 1] = float("nan")


def wider(t):
    t["features"] = torch.cat([t["features"], t["features"][:, :1]], dim=1)


CASES = {
    "flipped bit": (flip_a_bit, "its sha256 differs"),
    "missing tensor": (lambda f: rewrite(f, lambda t: t.pop("features")), "no 'features' tensor"),
    "wrong width": (lambda f: rewrite(f, wider), "expected torch.float32 (16, "),
    "nan": (lambda f: rewrite(f, nan), "hold NaN or inf in 1 of 16 windows"),
}


@pytest.mark.parametrize("case", CASES)
def test_a_damaged_entry_is_reported_in_one_line_and_nothing_is_published(ws, case):
    damage, what = CASES[case]
    f = entry_file(ws)
    damage(f)
    r = sefa(ws, "distill")
    assert r.returncode == 1, r.stderr[-2000:]
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith(f"error: {f}: damaged features cache entry, not used: "), last
    assert what in last and "--force" in last and "Traceback" not in r.stderr
    assert not (ws / "distill").exists()
    assert not list((ws / "runs").glob("distill/*")) and not list((ws / "runs").glob("distill/.*"))


def test_force_encodes_a_damaged_entry_again(ws):
    from sefa_model.data.features import META_FILE

    f = entry_file(ws)
    good = load_file(str(f))
    rewrite(f, nan)
    r = sefa(ws, "distill", "--force")
    assert r.returncode == 0, r.stderr[-2000:]
    assert f"frozen features: {f}: damaged (" in r.stderr and "encoding again (--force)" in r.stderr
    assert (ws / "distill" / "manifest.json").exists()
    again = load_file(str(f))
    torch.testing.assert_close(again["features"], good["features"], rtol=0, atol=0)
    assert (f.parent / META_FILE).exists()
    r = sefa(ws, "distill", "--force")  # the rebuilt entry is read, checksum and all
    assert r.returncode == 0 and "windows read from" in r.stderr, r.stderr[-2000:]


def test_non_finite_features_are_never_cached(tmp_path, monkeypatch):
    """The encoder's own NaN (a policy with non-finite weights) is an error, not an entry."""
    from sefa_data.errors import SefaInputError
    from sefa_model.data import features

    class Encoder:
        out_dim = 2

    class Model:
        obs_encoder = Encoder()

    bad = torch.ones(3, 2)
    bad[1, 0] = float("inf")
    monkeypatch.setattr(features, "window_features", lambda *a, **k: bad)
    monkeypatch.setattr(features, "features_key", lambda *a, **k: "ab" * 32)
    with pytest.raises(SefaInputError, match="NaN or inf features for 1 of 3 training windows "
                                             r"\(the first: window 11\)"):
        features.cached_window_features(Model(), None, np.array([10, 11, 12]),
                                        torch.device("cpu"), tmp_path / "cache")
    assert not (tmp_path / "cache").exists() or not any((tmp_path / "cache").iterdir())


def test_an_entry_without_a_checksum_is_encoded_again(tmp_path, monkeypatch):
    """An entry an older sefa wrote (no sha256 in meta.json) is not trusted: encoded again,
    with a line saying so, and then read back checked."""
    import json

    from sefa_model.data import features

    class Encoder:
        out_dim = 2

    class Model:
        obs_encoder = Encoder()

    calls = []
    monkeypatch.setattr(features, "window_features",
                        lambda *a, **k: calls.append(1) or torch.ones(3, 2))
    monkeypatch.setattr(features, "features_key", lambda *a, **k: "cd" * 32)
    windows, cache, lines = np.array([1, 2, 3]), tmp_path / "cache", []

    def get():
        return features.cached_window_features(Model(), None, windows, torch.device("cpu"),
                                               cache, log=lines.append)

    get()
    (entry,) = cache.iterdir()
    meta = json.loads((entry / "meta.json").read_text())
    del meta["sha256"]
    (entry / "meta.json").write_text(json.dumps(meta))
    get()
    assert len(calls) == 2 and any("written without a checksum" in line for line in lines)
    get()
    assert len(calls) == 2 and lines[-1].startswith("frozen features: 3 windows read from")
