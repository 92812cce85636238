"""The mirror-symmetry reduction of the LMIs (synth.symmetry): detected when it holds, and lossless."""

import numpy as np
import pytest

from synth.augmented import AugmentedModel
from synth.design import synthesize
from synth.fuzzy import NTSModel
from synth.lmi import Theorem2LMIs, design_coordinates
from synth.options import DesignOptions
from synth.params import OperatingBounds, VehicleParams
from synth.robust import H2LMIs, error_scales, noise_inputs
from synth.symmetry import Parametrisation, physical_mirror_sign
from tests.tolerances import FORMULA_EQUALITY_ATOL, LAST_BITS_ATOL


def _coordinates(bounds: OperatingBounds, order: int = 3):
    aug = AugmentedModel.build(NTSModel.build(VehicleParams(), bounds), order)
    return aug, design_coordinates(aug)


@pytest.mark.parametrize("order", [1, 2, 3])
def test_the_paper_bounds_are_mirror_symmetric(order):
    """S A_i S = A_sigma(i) with sigma swapping the rules at r_min and r_max; C and the DMVT term invariant."""
    aug, dc = _coordinates(OperatingBounds(), order)
    sym = dc.mirror_symmetry()
    assert sym is not None
    # rules (V low, r low), (V low, r high), (V high, r low), (V high, r high): the mirror swaps r
    assert sym.rule_map == (1, 0, 3, 2)
    S = np.diag(physical_mirror_sign(aug.n))
    for i, j in enumerate(sym.rule_map):
        np.testing.assert_allclose(S @ aug.A_bar[i] @ S, aug.A_bar[j], atol=LAST_BITS_ATOL)
    np.testing.assert_array_equal(np.diag([1.0, -1.0]) @ aug.C_bar @ S, aug.C_bar)


def test_asymmetric_yaw_rate_bounds_have_no_mirror_symmetry():
    _, dc = _coordinates(OperatingBounds(r_min_radps=-0.55, r_max_radps=0.4))
    assert dc.mirror_symmetry() is None


def test_the_reduction_poses_one_lmi_per_mirror_orbit():
    _, dc = _coordinates(OperatingBounds())
    var = Parametrisation(dc.mirror_symmetry())
    pairs = var.pairs(4, 4)
    assert len(pairs) == 8
    sigma = (1, 0, 3, 2)
    orbits = {frozenset({(i, j), (sigma[i], sigma[j])}) for i in range(4) for j in range(4)}
    assert {o for o in orbits if any(p in o for p in pairs)} == orbits
    assert len(var.pairs(4, 1)) == 2  # common P: one LMI per orbit of rules
    full = Theorem2LMIs(dc, decoupled=False, use_symmetry=False)
    reduced = Theorem2LMIs(dc, decoupled=False)
    assert (full.n_lmis, reduced.n_lmis) == (16, 8)


def test_the_reduced_robust_design_reaches_the_full_designs_optimum():
    """Lossless: the H2 optimum over mirror-invariant points equals the optimum over all points."""
    options = DesignOptions()
    aug = AugmentedModel.build(NTSModel.build(VehicleParams(), OperatingBounds()), options.fault_order)
    dc = design_coordinates(aug, state_scales=error_scales(aug, options.noise))
    inputs = noise_inputs(aug, options.noise)
    optimum = {}
    for use in (False, True):
        lmis = H2LMIs(dc, inputs, lyapunov="fuzzy", margin=options.margin, alpha=0.995, use_symmetry=use)
        assert (lmis.symmetry is not None) == use
        assert lmis.solve("CLARABEL", 60.0).status in ("optimal", "optimal_inaccurate")
        optimum[use] = float(lmis.problem.value)
    # equal up to the solver's accuracy (both 'optimal'; measured 1.2e-4 apart with Clarabel 0.11.1)
    assert optimum[True] == pytest.approx(optimum[False], rel=5e-4)


def test_a_reduced_design_is_verified_on_every_vertex_lmi_of_the_full_family(paper_gains):
    c = paper_gains.certificate
    assert c.symmetry == "mirror"
    assert c.n_lmis_solved == 8 and c.n_lmis_verified == 32
    # the fuzzy Lyapunov matrices of mirrored rules are mirror images: S P_i S = P_sigma(i)
    S = np.diag(np.sign(np.diag(paper_gains.T @ np.diag(physical_mirror_sign(9)) @ np.linalg.inv(paper_gains.T))))
    for i, j in enumerate((1, 0, 3, 2)):
        np.testing.assert_allclose(S @ paper_gains.P[i] @ S, paper_gains.P[j], atol=FORMULA_EQUALITY_ATOL)


def test_asymmetric_bounds_are_designed_in_full_and_verified():
    bounds = OperatingBounds(r_min_radps=-0.55, r_max_radps=0.4)
    gains = synthesize(bounds=bounds, options=DesignOptions(design="paper", optimise_decay_rate=False))
    c = gains.certificate
    assert c.symmetry == "none" and c.n_lmis_solved == 16 and c.verified
