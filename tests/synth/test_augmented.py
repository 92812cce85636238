import numpy as np
import pytest

from synth.augmented import AugmentedModel, difference_coordinates, fault_chain_matrix
from synth.errors import BadParameters
from synth.fuzzy import NTSModel
from synth.params import OperatingBounds, VehicleParams
from tests.tolerances import FORMULA_EQUALITY_ATOL

NTS = NTSModel.build(VehicleParams(), OperatingBounds())


def test_order_3_is_the_triple_integrator_of_eq_17():
    I = np.eye(2)
    Z = np.zeros((2, 2))
    expected = np.block([[Z, I, Z], [Z, Z, I], [I, -3 * I, 3 * I]])
    np.testing.assert_array_equal(fault_chain_matrix(3), expected)


@pytest.mark.parametrize("order", [1, 2, 3])
def test_fault_chain_has_all_poles_at_one(order):
    chain = fault_chain_matrix(order)
    # (z - 1)^q per channel: (chain - I)^q = 0 and (chain - I)^(q-1) != 0
    shifted = chain - np.eye(chain.shape[0])
    assert np.allclose(np.linalg.matrix_power(shifted, order), 0)
    if order > 1:
        assert not np.allclose(np.linalg.matrix_power(shifted, order - 1), 0)


@pytest.mark.parametrize("order", [1, 2, 3])
def test_augmented_matrices_of_eq_18(order):
    aug = AugmentedModel.build(NTS, order)
    n = 3 + 2 * order
    assert aug.A_bar.shape == (4, n, n) and aug.C_bar.shape == (2, n)
    np.testing.assert_array_equal(aug.A_bar[:, :3, :3], NTS.A)
    np.testing.assert_array_equal(aug.A_bar[:, :3, 3:5], np.broadcast_to(NTS.F, (4, 3, 2)))
    np.testing.assert_array_equal(aug.C_bar @ aug.G_bar, np.zeros((2, 1)))  # phi is not measured
    (term,) = aug.dmvt_terms  # the paper's model: phi = v_y^2 only
    assert (term.low, term.high) == (-3.0, 3.0) and term.name == "d(v_y^2)/dv_y"
    np.testing.assert_array_equal(term.matrix(), aug.G_bar @ aug.unit_row(1))


@pytest.mark.parametrize("order", [1, 2, 3])
def test_difference_coordinates_give_a_jordan_block(order):
    T = difference_coordinates(order)
    chain = fault_chain_matrix(order)
    n = 3 + 2 * order
    jordan = (T @ np.pad(chain, ((3, 0), (3, 0))) @ np.linalg.inv(T))[3:, 3:]
    expected = np.eye(2 * order) + np.eye(2 * order, k=2)
    np.testing.assert_allclose(jordan, expected, atol=FORMULA_EQUALITY_ATOL)
    assert T.shape == (n, n)


def test_bad_order_is_rejected():
    with pytest.raises(BadParameters, match="fault_order"):
        AugmentedModel.build(NTS, 4)
