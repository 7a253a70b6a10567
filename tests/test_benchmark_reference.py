"""The benchmarks' accuracy oracle: DOP853 on the embedding against the
closed-form (Jacobi elliptic) body momentum of the free rigid body."""

import sys
from pathlib import Path

import numpy as np
import pytest

from prkmk_jax.scenes import elliptic_momentum

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import _common

CASES = [
    (None, _common.INERTIA),
    (0, np.array([1.0, 2.0, 3.0])),
    (1, np.array([3.0, 1.0, 2.0])),
    (2, np.array([1.0, 10.0, 100.0])),
]


def _initial(seed):
    """(Q₀, Π₀) of a case: the paper's (seed None) or one of a random batch."""
    if seed is None:
        return _common.initial_conditions(None)
    qs, pis = _common.initial_conditions(4, seed=seed)
    return qs[seed], pis[seed]


@pytest.mark.parametrize("seed, inertia", CASES)
def test_dop853_reference_matches_elliptic_solution(seed, inertia):
    q0, pi0 = _initial(seed)
    ts = np.linspace(0.0, 20.0, 41)
    q, pi = _common.reference(q0, pi0, 20.0, inertia=inertia, t_eval=ts)
    exact = elliptic_momentum(pi0, inertia, ts)
    scale = np.linalg.norm(pi0)
    assert np.abs(exact - pi).max() < 1e-11 * scale
    # The oracle keeps the invariants it is not built to keep.
    inv = _common.invariants(q, pi, inertia)
    assert np.abs(inv["orthogonality"]).max() < 1e-11
    assert np.abs(inv["spatial momentum"] - inv["spatial momentum"][0]).max() < 1e-11 * scale


def test_both_elliptic_branches_are_exercised():
    """|Π|² above and below 2H·I_mid (dn on the largest / smallest axis)."""
    sides = set()
    for seed, inertia in CASES:
        _, pi0 = _initial(seed)
        two_h = pi0 @ (pi0 / inertia)
        sides.add(bool(pi0 @ pi0 > two_h * np.sort(inertia)[1]))
    assert sides == {True, False}


def test_growth_exponent_interval_brackets_a_random_walk_and_a_drift():
    """`round_off.py`'s bootstrap interval of the growth exponent: for running
    maxima of random walks it holds 0.5 and not 1, for a steady drift with
    small noise 1 and not 0.5."""
    import round_off

    rng = np.random.default_rng(7)
    steps = np.arange(1, 1001) * 1000.0
    walks = np.cumsum(rng.normal(size=(64, 1000)), axis=1)
    drifts = steps * 1e-3 + np.cumsum(rng.normal(size=(64, 1000)), axis=1)
    for paths, inside, outside in ((walks, 0.5, 1.0), (drifts, 1.0, 0.5)):
        running_max = np.maximum.accumulate(np.abs(paths), axis=1)
        low, high = round_off.exponent_interval(steps, running_max)
        assert low < inside < high
        assert not low < outside < high
        assert high - low < 0.3
