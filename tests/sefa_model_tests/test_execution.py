"""Chunk execution (sefa_model/policy/execution.py), the one owner of how chunks become actions:
the selection math on hand-made arrays with exact expected numbers (ACT's ensembling weights,
backward coherence, forward contrast, Bidirectional Decoding's choice), every mode of the
`Executor` on a fake policy whose chunks are known (what it executes, when it predicts, the
noise it draws), the settings' checks (one line naming the option), and the record of a chosen
execution kept with a checkpoint."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from sefa_data.errors import ConfigError, SefaInputError
from sefa_model.policy.execution import (ChunkShape, Ensembler, ExecutionSettings, Executor,
                                         bid_choice, chunk_distances, coherence_cost,
                                         contrast_cost, decay_weights, default_settings,
                                         ensemble_weights)

SHAPE = ChunkShape(n_obs_steps=2, n_action_steps=4, horizon=6, action_dim=1)


# ---- the math

def test_ensemble_weights_are_acts_normalized_exponential_oldest_first():
    w = ensemble_weights(3, 0.5)
    raw = np.array([1.0, math.exp(-0.5), math.exp(-1.0)])
    np.testing.assert_allclose(w, raw / raw.sum(), rtol=1e-12)
    np.testing.assert_allclose(ensemble_weights(4, 0.0), [0.25] * 4)  # k = 0: the plain mean


def test_ensembler_averages_every_prediction_of_the_step_with_the_oldest_weighted_most():
    e = Ensembler(k=math.log(2))  # weights 1, 1/2, 1/4 before normalizing
    e.add(0, np.array([[0.0], [10.0], [20.0], [30.0]]))
    assert e.action(0)[0].tolist() == [0.0]
    e.add(1, np.array([[11.0], [21.0], [31.0], [41.0]]))
    a, n = e.action(1)
    assert n == 2 and a == pytest.approx([(10 + 11 / 2) / 1.5])
    e.add(2, np.array([[22.0], [32.0], [42.0], [52.0]]))
    a, n = e.action(4)  # chunk 0 ends at step 3: dropped, chunk 1 is now the oldest
    assert n == 2 and a == pytest.approx([(41 + 42 / 2) / 1.5]) and len(e.chunks) == 2
    with pytest.raises(ValueError, match="no prediction covers step 6"):
        e.action(6)


def test_coherence_is_the_decayed_weighted_mean_of_per_step_distances():
    np.testing.assert_allclose(decay_weights(3, 0.5), np.array([4, 2, 1]) / 7)
    prior = np.array([[0.0, 0.0], [0.0, 0.0]])  # 2 shared steps; the chunks are 3 long
    chunks = np.array([[[3.0, 4.0], [0.0, 0.0], [100.0, 0.0]],   # 5 at the near step
                       [[0.0, 0.0], [6.0, 8.0], [100.0, 0.0]]])  # 10 at the far one
    # weights 2/3, 1/3 (decay 0.5); the third step is beyond the prior and does not count
    np.testing.assert_allclose(coherence_cost(chunks, prior, 0.5), [5 * 2 / 3, 10 / 3])
    np.testing.assert_allclose(coherence_cost(chunks, prior, 1.0), [2.5, 5.0])  # plain mean


def test_chunk_distance_is_the_mean_per_step_euclidean_norm():
    a = np.array([[[0.0, 0.0], [0.0, 0.0]]])
    b = np.array([[[3.0, 4.0], [0.0, 1.0]], [[0.0, 0.0], [0.0, 0.0]]])
    np.testing.assert_allclose(chunk_distances(a, b), [[3.0, 0.0]])


def test_forward_contrast_prefers_the_agreeing_samples_away_from_the_weak_policy():
    # four 1-step 1-D samples at 0, 1, 2, 10; k = 2 nearest others; weak samples at 10 and 11
    strong = np.array([0.0, 1.0, 2.0, 10.0])[:, None, None]
    weak = np.array([10.0, 11.0])[:, None, None]
    own = np.array([(1 + 2) / 2, (1 + 1) / 2, (1 + 2) / 2, (8 + 9) / 2])
    np.testing.assert_allclose(contrast_cost(strong, None), own)
    near_weak = np.array([(10 + 11) / 2, (9 + 10) / 2, (8 + 9) / 2, (0 + 1) / 2])
    np.testing.assert_allclose(contrast_cost(strong, weak), own - near_weak)
    assert int(np.argmin(contrast_cost(strong, weak))) == 0  # 1.5 - 10.5 = -9


def test_bid_keeps_the_most_coherent_third_then_contrasts():
    # six samples, keep 6 // 3 = 2 most coherent with the prior (0): samples 1 and 2;
    # contrast alone would pick one of the four near 5 (their k = 3 nearest are near), never 1
    strong = np.array([5.0, 0.1, -0.2, 5.1, 5.05, 4.9])[:, None, None]
    prior = np.array([[0.0]])
    np.testing.assert_allclose(contrast_cost(strong, None)[[0, 1]], [0.25 / 3, (0.3 + 4.8 + 4.9) / 3])
    assert bid_choice(strong, None, prior, 0.9) == 1  # |0.1| + 0.3 < |-0.2| + 0.3
    # weak samples near 0.1 push the choice to the other coherent one
    weak = np.array([0.1, 0.1, 0.1, 9.0, 9.0, 9.0])[:, None, None]
    assert bid_choice(strong, weak, prior, 0.9) == 2
    assert bid_choice(strong, None, None, 0.9) == 0  # no prior: contrast alone (0 and 4 tie)


# ---- the executor on a fake policy

class Chunks:
    """Call k answers chunk k (k = 0, 1, ...): sample j of it is 100 k + 10 j + [0, 1, ..., 5]
    (the step index); `seen` keeps each call's observations and noise."""

    def __init__(self, pick=None):
        self.calls, self.seen = 0, []

    def __call__(self, obs, noise, generator):
        self.seen.append(({k: v.copy() for k, v in obs.items()}, noise.copy()))
        n = noise.shape[0]
        out = (100.0 * self.calls + 10.0 * np.arange(n)[:, None] + np.arange(SHAPE.horizon))
        self.calls += 1
        return out[:, :, None].astype(np.float32)


def run(ex: Executor, n: int) -> tuple[list[float], list[int]]:
    actions, plans = [], []
    for t in range(n):
        frame = {"x": np.array([float(t)], np.float32)}
        if ex.steps_to_decision == 0:
            plans.append(t)
        actions.append(float(ex.action(frame)[0]))
    return actions, plans


def test_receding_executes_replan_every_actions_from_the_current_frame_on():
    # index 1 (n_obs_steps - 1) is the current step: chunk k's actions are 100 k + 1, + 2, ...
    f = Chunks()
    actions, plans = run(Executor(default_settings(4), f, SHAPE), 6)
    assert plans == [0, 4] and actions == [1, 2, 3, 4, 101, 102]
    actions, plans = run(Executor(ExecutionSettings("receding", 2), Chunks(), SHAPE), 5)
    assert plans == [0, 2, 4] and actions == [1, 2, 101, 102, 201]
    # the history: the first frame repeated, then the newest n_obs_steps frames
    np.testing.assert_array_equal(f.seen[0][0]["x"], [[[0.0], [0.0]]])
    np.testing.assert_array_equal(f.seen[1][0]["x"], [[[3.0], [4.0]]])


def test_ensemble_predicts_every_step_and_averages_what_covers_it():
    ex = Executor(ExecutionSettings("ensemble", ensemble_k=0.0), Chunks(), SHAPE)
    actions, plans = run(ex, 3)
    # step 1: chunk 0's 2 and chunk 1's 101; step 2: 3, 102, 201
    assert plans == [0, 1, 2] and actions == [1, pytest.approx(51.5), pytest.approx(102)]
    assert ex.count == 3 and ex.replanned


def test_coherent_keeps_the_sample_nearest_the_previous_plan():
    """Samples differ by 10 j; at step 1 the previous plan says 2, 3, 4, 5 for steps 1..4 and
    the samples say 101 + 10 j, ...: sample 0 is nearest. A fake whose second call's samples
    descend instead (sample j = 100 - 10 j) makes the last sample the nearest."""
    ex = Executor(ExecutionSettings("coherent", samples=3), Chunks(), SHAPE)
    actions, _ = run(ex, 2)
    assert actions == [1, 101]

    class Descending(Chunks):
        def __call__(self, obs, noise, generator):
            out = super().__call__(obs, noise, generator)
            return out if self.calls == 1 else out[::-1] - 60.0  # 40 + 10 j' ... sample 2 = 40
    ex = Executor(ExecutionSettings("coherent", samples=3), Descending(), SHAPE)
    actions, _ = run(ex, 2)
    assert actions == [1, 41]  # sample 2 of call 1: 100 + 0 + 1 - 60 (reversed: j = 0 last)


def test_a_non_finite_chunk_is_refused_naming_the_step_and_the_episode():
    """A NaN anywhere in the samples (even one coherence would not choose) stops the episode
    with one error; nothing of the chunk is executed. The weaker policy's are checked too."""
    from sefa_data.errors import NonFiniteError

    class NaNAt(Chunks):
        def __call__(self, obs, noise, generator):
            out = super().__call__(obs, noise, generator)
            if self.calls == 2:
                out[-1, 3, 0] = np.nan  # the last sample of the second decision
            return out
    ex = Executor(ExecutionSettings("coherent", replan_every=2, samples=3), NaNAt(), SHAPE,
                  seed=100_007)
    with pytest.raises(NonFiniteError, match="the policy predicted a non-finite action chunk "
                                             r"\(NaN or Inf\) at step 2 of the episode seeded "
                                             "100007: nothing of it is executed"):
        run(ex, 3)
    assert ex.t == 2  # the steps before it executed, this one did not
    bad_weak = lambda obs, noise, generator: np.full((noise.shape[0], SHAPE.horizon, 1), np.inf)
    ex = Executor(ExecutionSettings("bid", samples=3, weak="w"), Chunks(), SHAPE, weak=bad_weak)
    with pytest.raises(NonFiniteError, match=r"the weaker policy \(--weak\) predicted"):
        run(ex, 1)


def test_coherence_compares_the_plans_for_the_same_steps():
    """At step 1 the previous plan (0..5, made at step 0) says 2, 3, 4, 5 for steps 1..4;
    sample 1 (1..6) says the same, sample 0 (0..5) says it one step late."""
    plans = iter([np.arange(6.0)[None].repeat(2, 0), np.stack([np.arange(6.0), np.arange(1.0, 7.0)])])
    ex = Executor(ExecutionSettings("coherent", samples=2), lambda o, n, g: next(plans)[:, :, None],
                  SHAPE)
    actions, _ = run(ex, 2)
    assert actions == [1, 2]


def test_the_executor_draws_the_noise_predict_action_would_draw():
    """One sample: exactly torch.randn from the episode's generator (what `sefa eval` drew
    before executions existed, so its results are unchanged); N samples: one (N, H, Da) draw."""
    f = Chunks()
    ex = Executor(default_settings(4), f, SHAPE, seed=7)
    ex.action({"x": np.zeros(1, np.float32)})
    want = torch.randn((1, 6, 1), generator=torch.Generator().manual_seed(7)).numpy()
    np.testing.assert_array_equal(f.seen[0][1], want)
    ex.reset(7)  # a new episode with the same seed draws the same noise again
    ex.action({"x": np.zeros(1, np.float32)})
    np.testing.assert_array_equal(f.seen[1][1], want)
    g = Chunks()
    ex = Executor(ExecutionSettings("coherent", samples=5), g, SHAPE, seed=7)
    ex.action({"x": np.zeros(1, np.float32)})
    # 5 noises for the one observation, which the sampler encodes once
    assert g.seen[0][1].shape == (5, 6, 1) and g.seen[0][0]["x"].shape == (1, 2, 1)


def test_bid_draws_the_weak_policys_samples_too():
    strong, weak = Chunks(), Chunks()
    ex = Executor(ExecutionSettings("bid", samples=6, weak="w"), strong, SHAPE, weak=weak)
    run(ex, 3)
    assert strong.calls == weak.calls == 3 and weak.seen[0][1].shape == (6, 6, 1)
    with pytest.raises(ValueError, match="weaker policy"):
        Executor(ExecutionSettings("bid", samples=6, weak="w"), strong, SHAPE)


def test_a_frame_missing_a_key_the_decision_needs_is_one_clear_error():
    ex = Executor(default_settings(4), Chunks(), SHAPE)
    ex.action({"x": np.zeros(1), "img": np.zeros(1)})
    for _ in range(3):
        ex.action({"x": np.zeros(1)})  # frames no decision sees may lack the image
    with pytest.raises(SefaInputError, match="observation 'img' is missing"):
        ex.action({"x": np.zeros(1)})


BAD = [
    (dict(mode="act"), "--execution: not one of receding, ensemble, coherent, bid: 'act'"),
    (dict(replan_every=5), "--replan-every: 5 is outside 1..4"),
    (dict(replan_every=0), "--replan-every: 0 is too small"),
    (dict(samples=4), "--samples: 4 samples need the coherent or bid mode"),
    (dict(mode="coherent", samples=1), "--samples: coherent chooses among at least 2"),
    (dict(mode="ensemble", ensemble_k=float("nan")), "--ensemble-k: nan is not a finite number"),
    (dict(mode="coherent", decay=0.0), "--decay: 0 is too small"),
    (dict(mode="bid"), "--weak: bid contrasts against a weaker policy"),
    (dict(mode="coherent", weak="train"), "--weak: a weaker policy is used by --execution bid"),
    (dict(decay=0.5), "--decay: a decay weighs coherence, which coherent and bid use, not receding"),
    (dict(mode="coherent", ensemble_k=0.1), "--ensemble-k: k weighs ensembled predictions, which "
                                            "ensemble uses, not coherent"),
]


@pytest.mark.parametrize("given,line", BAD, ids=[b[1].split(":")[0] + str(i) for i, b in enumerate(BAD)])
def test_bad_settings_are_one_line_naming_the_option(given, line):
    with pytest.raises(ConfigError) as e:
        ExecutionSettings(**given).resolved(4)
    assert str(e.value).startswith(line)


def test_bad_settings_read_from_a_file_name_the_file_and_its_key():
    """sefa.yaml's `execution:` section: the line names the file and the key the user wrote,
    not an option they never typed."""
    with pytest.raises(ConfigError) as e:
        ExecutionSettings("receding", 50).resolved(8, source="sefa.yaml")
    assert str(e.value).startswith("sefa.yaml: execution.replan_every: 50 is outside 1..8")
    with pytest.raises(ConfigError) as e:
        ExecutionSettings("ensemble", decay=0.5).resolved(8, source="sefa.yaml")
    assert str(e.value).startswith("sefa.yaml: execution.decay: a decay weighs coherence")
    assert ExecutionSettings("coherent").resolved(8, source="sefa.yaml").samples == 16


def test_settings_resolve_their_defaults_and_round_trip_through_json():
    assert default_settings(8) == ExecutionSettings("receding", 8, 1)
    assert default_settings(8).is_default(8) and not ExecutionSettings("receding", 4).resolved(8).is_default(8)
    c = ExecutionSettings("coherent").resolved(8)
    assert (c.replan_every, c.samples, c.label) == (1, 16, "coherent K=1 N=16")
    again = ExecutionSettings.from_json(json.loads(json.dumps(c.to_json())))
    assert again == c
    with pytest.raises(ConfigError, match="unknown key 'sample'"):
        ExecutionSettings.from_json({"mode": "coherent", "sample": 3})


# ---- the chosen execution, kept with the checkpoint

def test_a_chosen_execution_is_read_back_only_for_its_weights_and_sampler(tmp_path):
    from sefa_model.policy.execution import load_choice, save_choice

    ckpt = tmp_path / "ckpt"
    ckpt.mkdir()
    (ckpt / "config.json").write_text("{}")
    (ckpt / "checksums.json").write_text('{"a": 1}')
    chosen = ExecutionSettings("receding", 4, 1)
    save_choice(ckpt, chosen, "euler-1", {"validation_seeds": [200000, 200049]})
    assert load_choice(ckpt, "euler-1") == chosen and load_choice(ckpt) == chosen
    assert load_choice(ckpt, "rk45") is None  # chosen for another sampler setting
    (ckpt / "checksums.json").write_text('{"a": 2}')  # retrained: other weights
    assert load_choice(ckpt, "euler-1") is None
    (ckpt / "execution.json").write_text("{not json")
    with pytest.raises(SefaInputError, match="execution.json.*unreadable"):
        load_choice(ckpt)


def test_a_checkpoint_with_a_chosen_execution_still_verifies_and_resumes(tmp_path):
    """The record is written beside the checkpoint after its checksums: the checkpoint's own
    checks (load, `sefa train --resume`) still pass, and any other file added still fails them."""
    from sefa_model.policy.checkpoint import verify_checksums, write_checksums
    from sefa_model.policy.execution import save_choice

    ckpt = tmp_path / "ckpt"
    ckpt.mkdir()
    (ckpt / "config.json").write_text("{}")
    (ckpt / "model.safetensors").write_bytes(b"weights")
    write_checksums(ckpt)
    save_choice(ckpt, ExecutionSettings("receding", 4, 1), "euler-1", {})
    assert verify_checksums(ckpt)
    (ckpt / "notes.txt").write_text("added later")
    with pytest.raises(SefaInputError, match="notes.txt.*not recorded in checksums.json"):
        verify_checksums(ckpt)


def test_an_executions_cost_per_control_step():
    from sefa_model.eval.latency import execution_cost

    c = execution_cost(ExecutionSettings("receding", 4).resolved(8), 2.0, 80.0, worst_ms=13.0)
    assert c == {"execution": "receding K=4", "decision_ms": 2.0, "mean_step_ms": 0.5,
                 "worst_step_ms": 13.0, "period_ms": 12.5, "fits": False}
    assert execution_cost(default_settings(8), 2.0, None)["fits"] is None
    assert execution_cost(default_settings(8), 2.0, 80.0)["fits"] is True


def test_the_default_candidates():
    from sefa_model.policy.execution import candidates, parse_spec

    labels = [c.label for c in candidates(8)]
    assert labels == ["receding K=1", "receding K=2", "receding K=4", "receding K=8",
                      "ensemble K=1", "coherent K=1 N=16", "coherent K=2 N=16",
                      "coherent K=4 N=16"]
    assert [c.label for c in candidates(2, weak="train@euler-1")][-2:] == ["bid K=1 N=16",
                                                                           "bid K=2 N=16"]
    assert parse_spec("coherent-2x8").resolved(8) == ExecutionSettings("coherent", 2, 8)
    with pytest.raises(ConfigError, match="--candidate: 'fast' is not MODE"):
        parse_spec("fast")
