import numpy as np
import pytest

import prkmk_jax as pk
from prkmk_jax.tableaus import PartitionedTableau, bicoloured_trees


def test_bicoloured_tree_counts():
    # Number of bicoloured rooted trees with n nodes (OEIS A000151): 2, 4, 14, 52, 214.
    assert [len(bicoloured_trees(n)) for n in range(1, 6)] == [2, 4, 14, 52, 214]


@pytest.mark.parametrize("tab", pk.tableaus.ALL_TABLEAUS, ids=lambda t: t.name)
def test_declared_order_is_exact(tab):
    assert tab.violated_conditions(tab.order) == []
    assert tab.violated_conditions(tab.order + 1) != []  # not secretly of higher order
    assert tab.is_symplectic()


def test_paper_tableaus():
    se = pk.symplectic_euler
    assert se.a_first.tolist() == [[1.0]] and se.a_second.tolist() == [[0.0]]
    sv = pk.stormer_verlet
    assert sv.a_first.tolist() == [[0, 0], [0.5, 0.5]] and sv.a_second.tolist() == [[0.5, 0], [0.5, 0]]
    assert pk.stormer_verlet_adjoint.a_first.tolist() == sv.a_second.tolist()


def test_user_pair_is_accepted():
    # Explicit midpoint on both components (a non-symplectic order-2 pair).
    a = np.array([[0, 0], [0.5, 0]])
    t = PartitionedTableau("midpoint", a, np.array([0, 1.0]), np.array([0, 0.5]), a, np.array([0, 1.0]), np.array([0, 0.5]), 2)
    assert t.num_stages == 2 and not t.is_symplectic()
    assert t.a_first.flags.writeable is False


def test_bad_tableaus():
    one = np.array([1.0])
    with pytest.raises(ValueError, match="row sums"):
        PartitionedTableau("x", np.array([[1.0]]), one, np.array([0.5]), np.array([[0.0]]), one, np.array([0.0]), 1)
    with pytest.raises(ValueError, match="sums to"):
        PartitionedTableau("x", np.array([[1.0]]), np.array([0.9]), one, np.array([[0.0]]), one, np.array([0.0]), 1)
    with pytest.raises(ValueError, match="order conditions"):
        PartitionedTableau("x", np.array([[1.0]]), one, one, np.array([[0.0]]), one, np.array([0.0]), 2)
    with pytest.raises(ValueError, match="shape"):
        PartitionedTableau("x", np.eye(2), one, one, np.array([[0.0]]), one, np.array([0.0]), 1)
    with pytest.raises(ValueError, match="order must be"):
        PartitionedTableau("x", np.array([[1.0]]), one, one, np.array([[0.0]]), one, np.array([0.0]), 0)


def test_plan_of_the_tableau_alone():
    """With every slope depending on the whole stage point, the plan is the
    tableau's own block structure."""
    from prkmk_jax.methods.stage_plan import COUPLED, Explicit, Implicit, plan_stages

    assert plan_stages(pk.symplectic_euler, COUPLED) == (Implicit(((0, 0), (0, 1))),)
    assert plan_stages(pk.stormer_verlet, COUPLED) == (Implicit(((0, 0), (0, 1))), Implicit(((1, 0), (1, 1))))
    assert plan_stages(pk.lobatto_iiia_iiib4, COUPLED) == (Implicit(tuple((i, c) for i in range(3) for c in (0, 1))),)
    a = np.array([[0, 0], [1.0, 0]])
    heun = PartitionedTableau("heun", a, np.array([0.5, 0.5]), np.array([0, 1.0]), a, np.array([0.5, 0.5]), np.array([0, 1.0]), 2)
    assert plan_stages(heun, COUPLED) == (Explicit(0, (0, 1)), Explicit(1, (0, 1)))


def test_tableaus_are_equal_where_their_coefficients_are():
    """Equality and hash follow the arrays and the order, not the name: a
    renamed copy is the same method (one compiled program), a changed weight
    or order is another."""
    sv = pk.stormer_verlet
    renamed = PartitionedTableau("SV, renamed", sv.a_first, sv.b_first, sv.c_first, sv.a_second, sv.b_second, sv.c_second, sv.order)
    assert renamed == sv and hash(renamed) == hash(sv)
    assert pk.PRKMK(pk.Cotangent(pk.SO3), tableau=renamed) == pk.PRKMK(pk.Cotangent(pk.SO3), tableau=sv)
    lower = PartitionedTableau("SV, order 1", sv.a_first, sv.b_first, sv.c_first, sv.a_second, sv.b_second, sv.c_second, 1)
    assert lower != sv
    assert sv.swapped() != sv  # Lobatto IIIB–IIIA: the same arrays in the other parts
    assert pk.lobatto_iiia_iiib4 != sv and sv != "stormer_verlet"
