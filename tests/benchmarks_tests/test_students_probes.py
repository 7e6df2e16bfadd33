"""The students probes' two pieces of arithmetic that their conclusions rest on
(benchmarks/students_probes.py; the probes themselves are not run in CI): a deepened student
starts as exactly its teacher, and the nearest-chunk distance is sefa's chunk distance."""

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
    from sefa_model.networks import MlpHead

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
    from sefa_model.couplings import chunk_distance

    g = torch.Generator().manual_seed(1)
    x, ref = torch.randn(3, 5, 16, 2, generator=g), torch.randn(3, 5, 16, 2, generator=g)
    got = probes.nearest(x, ref)
    want = np.array([min(chunk_distance(x[i, a][None].numpy(), ref[i, b][None].numpy())[0]
                         for b in range(5)) for i in range(3) for a in range(5)])
    np.testing.assert_allclose(got, want, rtol=1e-5)
    # a chunk that is one of the references is at distance 0
    assert probes.nearest(ref, ref).max() < 1e-5
