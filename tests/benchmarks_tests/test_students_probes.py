"""The students probes' arithmetic that their conclusions rest on (benchmarks/students_probes.py;
the probes themselves are not run in CI): a deepened student starts as exactly its teacher, the
nearest-chunk distance is sefa's chunk distance, the energy student's batches hold whole groups
of one window's couplings, and its energy score is the formula and ranks a collapsed student
below a faithful one."""

from __future__ import annotations

import types

import numpy as np
import pytest
import torch


@pytest.fixture(scope="module")
def probes():
    from benchmark_module import load

    return load("students_probes")


def test_deepened_student_answers_as_its_teacher_until_trained(probes):
    from sefa_model.nets.networks import MlpHead

    torch.manual_seed(0)
    teacher = types.SimpleNamespace(head=MlpHead(2, 16, 40, time_embed_dim=32, hidden_dims=(64, 64)))
    x, t, cond = torch.randn(8, 16, 2), torch.rand(8) * 999, torch.randn(8, 40)
    before = teacher.head(x, t, cond)
    student = probes.deepen(teacher, 3)
    assert len(student.head.blocks) == 5
    torch.testing.assert_close(student.head(x, t, cond), before, rtol=0, atol=0)
    # the new blocks are trainable: one gradient step moves the output
    loss = student.head(x, t, cond).square().mean()
    loss.backward()
    assert student.head.blocks[-1].fc2.weight.grad.abs().sum() > 0


def test_nearest_is_the_chunk_distance_to_the_closest_reference(probes):
    from sefa_model.data.couplings import chunk_distance

    g = torch.Generator().manual_seed(1)
    x, ref = torch.randn(3, 5, 16, 2, generator=g), torch.randn(3, 5, 16, 2, generator=g)
    got = probes.nearest(x, ref)
    want = np.array([min(chunk_distance(x[i, a][None].numpy(), ref[i, b][None].numpy())[0]
                         for b in range(5)) for i in range(3) for a in range(5)])
    np.testing.assert_allclose(got, want, rtol=1e-5)
    # a chunk that is one of the references is at distance 0
    assert probes.nearest(ref, ref).max() < 1e-5


def test_grouped_rows_are_distinct_couplings_of_one_window_per_group(probes):
    rows = probes.grouped_rows(n_windows=50, k=10, group=8, windows=32,
                               gen=torch.Generator().manual_seed(0)).view(32, 8)
    window = rows // 10
    assert (window == window[:, :1]).all() and (window < 50).all()
    assert all(len(set(r.tolist())) == 8 for r in rows)  # without replacement within a window


def test_energy_score_is_the_formula_and_punishes_a_student_pulled_to_the_mean(probes):
    g = torch.Generator().manual_seed(2)
    s, t = torch.randn(2, 3, 4, generator=g), torch.randn(2, 3, 4, generator=g)
    rms = lambda a, b: float(((a - b) ** 2).mean().sqrt())  # noqa: E731
    want = np.mean([np.mean([rms(s[w, i], t[w, j]) for i in range(3) for j in range(3)])
                    - 0.5 * np.mean([rms(s[w, i], s[w, j]) for i in range(3) for j in range(3) if i != j])
                    for w in range(2)])
    assert probes.energy_score(s, t).item() == pytest.approx(want, rel=1e-5)
    teacher = torch.randn(64, 8, 32, generator=g)
    mean = teacher.mean(1, keepdim=True).expand_as(teacher).clone().requires_grad_()
    faithful = torch.randn(64, 8, 32, generator=g)  # other draws of the same distribution
    assert probes.energy_score(faithful, teacher) < probes.energy_score(mean, teacher)
    probes.energy_score(mean, teacher).backward()  # equal chunks: the gradient stays finite
    assert torch.isfinite(mean.grad).all() and mean.grad.abs().sum() > 0
