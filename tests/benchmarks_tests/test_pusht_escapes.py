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


def test_the_difference_splits_into_the_escaped_seeds_and_the_others(pe):
    """Over the seeds both ran (seed 3 is only in a): a - b = 0.25 * ((0.1 - 0.9) + (0.5 - 0.5)
    + (0.8 - 0.4) + (0.2 - 0.6)); a's agent left on seeds 0 and 2."""
    a = [{"seed": s, "score": x, "escaped": e}
         for s, x, e in ((0, 0.1, True), (1, 0.5, False), (2, 0.8, True), (4, 0.2, False),
                         (3, 1.0, False))]
    b = [{"seed": s, "score": x, "escaped": e}
         for s, x, e in ((0, 0.9, False), (1, 0.5, True), (2, 0.4, False), (4, 0.6, True))]
    out = pe.split_difference(a, b)
    assert (out["n"], out["escaped"], out["other_escaped"]) == (4, 2, 2)
    assert out["minus"] == pytest.approx((-0.8 + 0.0 + 0.4 - 0.4) / 4)
    assert out["from_escaped"] == pytest.approx((-0.8 + 0.4) / 4)
    assert out["from_the_others"] == pytest.approx((0.0 - 0.4) / 4)
    assert out["from_escaped"] + out["from_the_others"] == pytest.approx(out["minus"])
