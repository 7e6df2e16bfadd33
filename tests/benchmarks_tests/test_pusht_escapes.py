"""benchmarks/pusht_escapes.py's arithmetic: when an episode counts as having left the arena, and
the clamp of sampled chunks to the demonstrated range, on exact arrays."""

from __future__ import annotations

import numpy as np
import pytest

from benchmark_module import load


@pytest.fixture(scope="module")
def pe():
    return load("pusht_escapes")


def test_an_episode_escapes_when_the_agent_leaves_the_walls_or_stops_being_finite(pe):
    inside = np.array([[5.0, 5.0], [256.0, 300.0], [506.0, 0.0], [512.0, 512.0]])
    assert not pe.escaped(inside)
    assert pe.escaped(np.vstack([inside, [[513.0, 200.0]]]))
    assert pe.escaped(np.vstack([inside, [[200.0, -0.5]]]))
    assert pe.escaped(np.vstack([inside, [[np.nan, 200.0]]]))
    assert pe.escaped(np.vstack([inside, [[np.inf, np.inf]]]))


def test_clamped_chunks_stay_in_the_range_per_dimension(pe):
    chunks = np.array([[[-5.0, 0.5], [0.0, 9.0]], [[2.0, -9.0], [1.0, 1.0]]])  # (N=2, T=2, Da=2)
    seen = []

    def sample(obs, noise, generator):
        seen.append((obs, noise, generator))
        return chunks

    out = pe.clamped(sample, np.array([-1.0, 0.0]), np.array([1.0, 2.0]))("o", "n", "g")
    assert seen == [("o", "n", "g")]
    np.testing.assert_array_equal(out, [[[-1.0, 0.5], [0.0, 2.0]], [[1.0, 0.0], [1.0, 1.0]]])
