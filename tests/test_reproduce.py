"""The paper's §5 experiments: invariants, the symplecticity diagnostic, and
the reproduce command."""

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import prkmk_jax as pk
from prkmk_jax import diagnostics
from prkmk_jax import reproduce as rp
from prkmk_jax.scenes import rigid_body as rb

RUNS = {r.name: r for r in rp.paper_runs()}


@pytest.fixture(scope="module")
def results():
    """Execute the §5 runs once (without the compile-heavy step Jacobian)."""
    names = [n for n in RUNS if not n.startswith("sym_so4")]
    return {n: rp.execute(RUNS[n], rb.PAPER_SEED, symplecticity=False) for n in names}


def test_initial_momentum_of_the_symmetric_body():
    y0 = rb.symmetric_initial_state(rb.random_rotation(rb.PAPER_SEED), rb.PAPER_MOMENTUM)
    q, p = np.asarray(y0.base.matrix), np.asarray(y0.fiber.matrix)
    np.testing.assert_allclose(q.T @ p - p.T @ q, np.asarray(pk.hat(jnp.asarray(rb.PAPER_MOMENTUM))), rtol=0, atol=1e-14)
    # so(4): the skew sinh⁻¹ is an arcsin of the eigen-angles
    m = (lambda a: 0.4 * (a - a.T))(np.random.default_rng(0).normal(size=(4, 4)))
    y4 = rb.symmetric_initial_state(rb.random_rotation(1, 4), m)
    q, p = np.asarray(y4.base.matrix), np.asarray(y4.fiber.matrix)
    np.testing.assert_allclose(q.T @ p - p.T @ q, m, rtol=0, atol=1e-14)


def test_skew_arcsinh_refuses_large_momenta():
    with pytest.raises(ValueError, match="no real skew solution"):
        rb.skew_arcsinh(np.asarray(pk.hat(jnp.array([0.0, 0.0, 2.5]))))
    with pytest.raises(ValueError, match="skew-symmetric"):
        rb.skew_arcsinh(np.eye(3))
    with pytest.raises(ValueError, match="no real skew solution"):
        rb.symmetric_initial_state(np.eye(3), np.array([0.0, 0.0, 2.5]))


@pytest.mark.parametrize("name", ["sym_SE_exp", "sym_SE_cayley", "sym_SV_exp", "sym_SV_cayley"])
def test_section_5_1_conservation(results, name):
    record, arrays = results[name]
    assert record["result"] == "successful"
    assert record["max_body_momentum_norm_drift"] <= 1e-12
    assert record["max_spatial_momentum_drift"] <= 1e-12
    for key in ("Q", "P"):
        m = arrays[key]
        assert np.abs(np.einsum("tji,tjk->tik", m, m) - np.eye(3)).max() <= 1e-13


@pytest.mark.parametrize("name", ["sym_SE_exp", "sym_SE_cayley", "sym_SE_exp_T1000"])
def test_section_5_1_symplectic_euler_energy_stays_in_a_band(results, name):
    record, _ = results[name]
    assert record["energy_error_last_quarter"] <= 1.5 * record["energy_error_first_quarter"], record
    assert record["max_abs_energy_error"] < 0.05


@pytest.mark.parametrize("name", ["unreduced_SE_exp", "unreduced_SE_cayley", "unreduced_SV_exp", "unreduced_SV_cayley"])
def test_section_5_2_momentum_conserved_on_the_semidirect_bundle(results, name):
    record, _ = results[name]
    assert record["max_body_momentum_norm_drift"] <= 1e-12
    assert record["max_spatial_momentum_drift"] <= 1e-12
    assert record["max_orthogonality_defect"] <= 1e-13


def test_section_5_2_energy_behaviour(results):
    """Symplectic Euler drifts (paper Fig. 5.3: towards a pole); the §5
    Störmer–Verlet pair conserves H: with η = 0 it sets u = h(Ωₙ + Ωₙ₊₁)/2 and
    Πₙ₊₁ = exp(−û)Πₙ, a rotation about u, so ΔH = (Πₙ₊₁ − Πₙ)·u/h = 0."""
    for coords in ("exp", "cayley"):
        se = results[f"unreduced_SE_{coords}"][0]
        assert se["final_energy_error"] < -0.5  # loses over a quarter of H₀ = 1.88 by T = 50
        sv = results[f"unreduced_SV_{coords}"][0]
        assert sv["max_abs_energy_error"] < 1e-11


def test_direct_product_loses_the_casimir(results):
    """On G×g the same explicit-in-Π symplectic Euler does not keep |Π|."""
    assert results["unreduced_direct_SE_exp"][0]["max_body_momentum_norm_drift"] > 0.1
    assert results["unreduced_SE_exp"][0]["max_body_momentum_norm_drift"] <= 1e-12


def test_an_equal_run_reuses_its_compiled_integration(results):
    """The fixture executed these runs; executing an equal run (a new `Run`
    object, as the command makes) compiles nothing and gives the same
    trajectory."""
    compiles = []

    def listener(event, duration, **_):
        if event == "/jax/core/compile/backend_compile_duration":
            compiles.append(duration)

    run = rp.paper_runs()[3]
    assert run == RUNS[run.name] and run is not RUNS[run.name]
    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        record, arrays = rp.execute(run, rb.PAPER_SEED, symplecticity=False)
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
    assert compiles == []
    np.testing.assert_array_equal(arrays["Pi"], results[run.name][1]["Pi"])
    assert record["max_abs_energy_error"] == results[run.name][0]["max_abs_energy_error"]


# --- the symplecticity diagnostic --------------------------------------------------
def _pendulum(t, y, args):
    return y.fiber.value, -jnp.sin(y.base.value)


def _classical_step_map(tab):
    method = pk.PRKMK(pk.Cartesian(pk.VectorSpace), pk.Exp(), tab)

    def step(z):
        y = pk.BundleElement(pk.VectorSpace(z[:1]), pk.VectorSpace(z[1:]))
        y1 = method.step(_pendulum, 0.0, y, 0.3).y
        return jnp.concatenate([y1.base.value, y1.fiber.value])

    return step


@pytest.mark.parametrize("tab", pk.tableaus.ALL_TABLEAUS, ids=lambda t: t.name)
def test_symplecticity_defect_vanishes_for_symplectic_prk(tab):
    defect = diagnostics.canonical_symplecticity_defect(_classical_step_map(tab), jnp.array([1.1, -0.4]))
    assert defect < 1e-13


def test_symplecticity_defect_detects_non_symplectic_rk():
    a = np.array([[0, 0], [0.5, 0]])
    midpoint = pk.PartitionedTableau(
        "explicit midpoint", a, np.array([0, 1.0]), np.array([0, 0.5]), a, np.array([0, 1.0]), np.array([0, 0.5]), 2
    )
    assert diagnostics.canonical_symplecticity_defect(_classical_step_map(midpoint), jnp.array([1.1, -0.4])) > 1e-3


def test_cotangent_chart_sees_the_exact_flow_as_symplectic():
    """In the canonical chart of T*SO(3) a near-exact flow map (20 classical
    RK4 steps on the embedding ℝ⁹×ℝ³, independent of the library's
    integrators) has a tiny defect and explicit Euler does not."""
    inertia = jnp.asarray(rb.PAPER_INERTIA)

    def rhs(g, pi):
        omega = pi / inertia
        return g @ pk.hat(omega), jnp.cross(pi, omega)

    def rk4(_, state, h=0.1 / 20):
        g, pi = state
        k1 = rhs(g, pi)
        k2 = rhs(g + h / 2 * k1[0], pi + h / 2 * k1[1])
        k3 = rhs(g + h / 2 * k2[0], pi + h / 2 * k2[1])
        k4 = rhs(g + h * k3[0], pi + h * k3[1])
        return g + h / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0]), pi + h / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])

    def flow(g, pi):
        return jax.lax.fori_loop(0, 20, rk4, (g, pi))

    def euler(g, pi):
        omega = pi / inertia
        return g @ pk.SO3.exp(0.1 * omega).matrix, pi + 0.1 * jnp.cross(pi, omega)

    g0, pi0 = jnp.asarray(rb.random_rotation(1)), jnp.asarray(rb.PAPER_MOMENTUM)
    assert float(jax.jit(lambda g, p: diagnostics.symplecticity_defect(flow, g, p))(g0, pi0)) < 1e-8
    assert float(jax.jit(lambda g, p: diagnostics.symplecticity_defect(euler, g, p))(g0, pi0)) > 1e-2


def test_canonical_chart_round_trip():
    g0 = jnp.asarray(rb.random_rotation(3))
    g = g0 @ pk.SO3.exp(jnp.array([0.2, -0.1, 0.3])).matrix
    pi = jnp.array([0.3, 0.1, -0.7])
    q, p = diagnostics.to_canonical(g0, g, pi)
    g1, pi1 = diagnostics.from_canonical(g0, q, p)
    np.testing.assert_allclose(g1, g, atol=1e-14)
    np.testing.assert_allclose(pi1, pi, atol=1e-14)


@pytest.mark.parametrize("angle", [0.0, 1e-5, 0.3, 2.0, 3.1])
def test_canonical_momentum_pairs_with_the_velocity(angle):
    """p is conjugate to q: ⟨Π, g⁻¹ġ⟩ = ⟨p, q̇⟩ for g = g₀ exp(q(t)), with
    g⁻¹ġ from `jax.jvp` of the exponential (not from the closed form of
    `to_canonical`), at angles up to near π."""
    g0 = jnp.asarray(rb.random_rotation(5))
    q = angle * jnp.array([0.48, -0.6, 0.64])
    pi = jnp.array([0.3, 0.1, -0.7])
    q_dot = jnp.array([-0.2, 0.5, 0.9])
    g, g_dot = jax.jvp(lambda q: g0 @ pk.SO3.exp(q).matrix, (q,), (q_dot,))
    q_back, p = diagnostics.to_canonical(g0, g, pi)
    np.testing.assert_allclose(q_back, q, atol=1e-12)
    np.testing.assert_allclose(jnp.dot(p, q_dot), jnp.dot(pi, pk.vee(g.T @ g_dot)), rtol=1e-13, atol=1e-15)


# --- the command -------------------------------------------------------------------
RECORD_FIELDS = {
    "run",
    "scene",
    "representation",
    "n",
    "coordinates",
    "tableau",
    "h",
    "T",
    "num_steps",
    "figure",
    "max_abs_energy_error",
    "energy_error_first_quarter",
    "energy_error_last_quarter",
    "final_energy_error",
    "max_body_momentum_norm_drift",
    "max_spatial_momentum_drift",
    "max_orthogonality_defect",
    "symplecticity_defect",
    "implicit_iterations_total",
    "implicit_iterations_max_per_step",
    "compile_time_s",
    "wall_time_s",
    "result",
}


# The §5 table of docs/reproduction.md: its row labels and the record fields of its columns.
TABLE_ROWS = {
    "symmetric, SE, exp (Fig 5.1)": "sym_SE_exp",
    "symmetric, SE, Cayley (Fig 5.1)": "sym_SE_cayley",
    "symmetric, SE, exp": "sym_SE_exp_T1000",
    "symmetric, SV, exp (Fig 5.2)": "sym_SV_exp",
    "symmetric, SV, Cayley (Fig 5.2)": "sym_SV_cayley",
    "T*SO(3), SE, exp (Fig 5.3)": "unreduced_SE_exp",
    "T*SO(3), SE, Cayley (Fig 5.3)": "unreduced_SE_cayley",
    "T*SO(3), SV, exp (Fig 5.4)": "unreduced_SV_exp",
    "T*SO(3), SV, Cayley (Fig 5.4)": "unreduced_SV_cayley",
    "G×g, SE, exp": "unreduced_direct_SE_exp",
    "G×g, SV, exp": "unreduced_direct_SV_exp",
    "SO(4)², SE, exp": "sym_so4_SE_exp",
    "SO(4)², SV, exp": "sym_so4_SV_exp",
}
TABLE_COLUMNS = (
    "max_abs_energy_error",
    "max_body_momentum_norm_drift",
    "max_spatial_momentum_drift",
    "max_orthogonality_defect",
    "symplecticity_defect",
)
ROUND_OFF = 1e-10


def _assert_documented_table_is_this_run(records):
    """Every entry of the §5 table of docs/reproduction.md above round-off is this run's
    value to its two printed digits; every entry below `ROUND_OFF` (which
    differs between machines in its digits) is still below it here."""
    page = (Path(__file__).resolve().parents[1] / "docs" / "reproduction.md").read_text()
    by_name = {r["run"]: r for r in records}
    table = [[cell.strip() for cell in line.strip().strip("|").split("|")] for line in page.splitlines() if line.startswith("| ")]
    rows = [row for row in table if row[0] in TABLE_ROWS]
    assert sorted(row[0] for row in rows) == sorted(TABLE_ROWS)
    for label, t_end, *cells in rows:
        record = by_name[TABLE_ROWS[label]]
        assert float(t_end) == record["T"], label
        for field, cell in zip(TABLE_COLUMNS, cells, strict=True):
            value, printed = record[field], cell
            if printed == "—":
                assert value is None, (label, field)
            elif float(printed) >= ROUND_OFF:
                assert float(f"{value:.1e}") == pytest.approx(float(printed), rel=1e-12), (label, field, value, printed)
            else:
                assert value < ROUND_OFF, (label, field, value)


@pytest.mark.end_to_end
def test_reproduce_command(tmp_path, capsys):
    # The README's job as it is, at the paper's time scale. --no-cache: the
    # test writes nothing to ~/.cache. The integrations the module's fixture ran are not
    # compiled again (`rp.execute` keeps one jitted integration per run).
    rp.main(["--out", str(tmp_path), "--jobs", "1", "--no-cache"])
    for i in range(1, 5):
        assert (tmp_path / f"fig5_{i}.png").stat().st_size > 10_000
    meta = json.loads((tmp_path / "results.json").read_text())
    assert len(meta["runs"]) == len(rp.paper_runs())
    for record in meta["runs"]:
        assert set(record) == RECORD_FIELDS
        assert record["result"] == "successful"
        assert (record["symplecticity_defect"] is None) == (record["n"] != 3)
    data = np.load(tmp_path / "trajectories.npz")
    assert {"sym_SE_exp/Q", "sym_SE_exp/P", "sym_SE_exp/t", "unreduced_SV_cayley/g", "unreduced_SV_cayley/Pi"} <= set(data.files)
    _assert_documented_table_is_this_run(meta["runs"])
    out = capsys.readouterr().out
    assert "max|ΔH|" in out
    # Progress: one line per finished run, as it finishes.
    runs = len(rp.paper_runs())
    assert all(f"[{i:2d}/{runs}]" in out for i in range(1, runs + 1))
