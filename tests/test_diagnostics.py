"""How `diagnostics` sorts the runs of a stability sweep, on runs built by
hand with a known outcome each."""

import jax.numpy as jnp
import numpy as np
import pytest

from prkmk_jax import diagnostics


def test_run_status_sorts_runs_by_how_they_ended():
    t = np.linspace(0.0, 1.0, 11)
    energy = np.stack(
        [
            2.0 + 0.05 * np.sin(t),  # |H/H₀ − 1| ≤ 0.021: bounded
            2.0 * (1.0 + 0.3 * t),  # 30 % drift
            2.0 + 0 * t,  # flat, but a stage failed
            np.where(t > 0.5, np.nan, 2.0),  # energy blew up
            2.0 + 0 * t,  # flat, but a state entry is inf
        ]
    )
    converged = np.array([True, True, False, False, True])
    states = np.zeros((5, 11, 3)).copy()
    states[4, 7, 1] = np.inf
    status = np.asarray(diagnostics.run_status(energy, converged, states))
    assert [diagnostics.RUN_STATUS[s] for s in status] == ["bounded", "energy drift", "implicit stage failed", "non-finite", "non-finite"]
    # the tolerance is on the relative drift: 30 % passes a 0.5 tolerance
    assert int(diagnostics.run_status(energy[1:2], converged[1:2], tolerance=0.5)[0]) == 0


def test_stability_threshold_is_the_last_value_before_the_first_failure():
    values = jnp.array([0.1, 0.2, 0.4, 0.8, 1.6])
    assert diagnostics.first_unbounded(np.array([0, 0, 1, 0, 3])) == 2
    assert diagnostics.first_unbounded(np.zeros(5, int)) is None
    assert diagnostics.stability_threshold(values, np.array([0, 0, 1, 0, 3])) == pytest.approx(0.2)  # bounded again later: ignored
    assert diagnostics.stability_threshold(values, np.zeros(5, int)) == pytest.approx(1.6)
    assert diagnostics.stability_threshold(values, np.array([2, 0, 0, 0, 0])) == 0.0
    with pytest.raises(ValueError, match="ascending"):
        diagnostics.stability_threshold(values[::-1], np.zeros(5, int))
    with pytest.raises(ValueError, match="one status per value"):
        diagnostics.stability_threshold(values, np.zeros(4, int))
