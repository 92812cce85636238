import pytest

from synth.augmented import AugmentedModel
from synth.design import synthesize
from synth.errors import Infeasible, SolverFailed, VerificationFailed
from synth.existence import check_decoupled_detectability, check_decoupling_rank, check_detectability
from synth.fuzzy import NTSModel
from synth.options import DesignOptions
from synth.params import OperatingBounds, VehicleParams

AUG = AugmentedModel.build(NTSModel.build(VehicleParams(), OperatingBounds()), 3)


def test_rank_condition_of_lemma_2_holds():
    check_decoupling_rank(AUG)  # rank(C_bar D_bar) = rank(D_bar) = 1


def test_decoupled_design_is_reported_impossible_with_its_reason():
    with pytest.raises(Infeasible) as info:
        check_decoupled_detectability(AUG)
    exc = info.value
    assert exc.details["eigenvalue"] == pytest.approx([1.0, 0.0], abs=1e-6)
    assert exc.details["yaw_rate_radps"] == 0.0
    assert "steering fault delta_f" in exc.details["states"]
    assert "lateral speed v_y" in exc.details["states"]
    assert "v_x = 5.0 m/s and r = 0.00 rad/s" in exc.reason
    assert "unobservable" in exc.reason and "'paper'" in exc.reason
    assert exc.details["undetectable_points"] == exc.details["grid_points"]


def test_synthesize_refuses_the_decoupled_design_before_solving():
    with pytest.raises(Infeasible, match="exact wind decoupling"):
        synthesize(options=DesignOptions(design="paper-decoupled"))


def test_the_design_without_decoupling_is_detectable():
    check_detectability(AUG)


def test_solving_the_decoupled_lmis_anyway_never_yields_gains():
    """Clarabel fails on them; SCS returns an 'optimal_inaccurate' point that the numpy check rejects."""
    options = DesignOptions(
        design="paper-decoupled",
        check_existence=False,
        fault_order=1,
        optimise_decay_rate=False,
        solver_time_limit_s=5.0,
    )
    with pytest.raises((SolverFailed, VerificationFailed)):
        synthesize(options=options)
