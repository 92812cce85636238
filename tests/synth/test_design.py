import dataclasses
import json

import numpy as np
import pytest

from synth.certificate import spectral_radius_grid, verify
from synth.design import synthesize
from synth.errors import VerificationFailed
from synth.gains import ObserverGains
from synth.lmi import Theorem2LMIs
from synth.options import DesignOptions


def test_certificate_summary(paper_gains):
    c = paper_gains.certificate
    assert c.verified and c.design == "paper" and c.fault_order == 3 and c.lyapunov == "fuzzy"
    assert c.n_lmis_verified == 32 and len(c.lmi_min_eigenvalues) == 32
    assert min(c.lmi_min_eigenvalues) > 0 and min(c.P_min_eigenvalues) > 0
    assert c.spectral_radius_max <= c.decay_rate < 1.0
    assert c.solver_status in ("optimal", "optimal_inaccurate") and "clarabel" in c.solver_version
    assert c.content_hash == paper_gains.content_hash()
    assert set(c.timings_s) >= {"existence_s", "solve_s", "total_s"}


def test_lyapunov_decrease_holds_on_a_dense_grid(paper_gains):
    """N(h, rho)^T P(h+) N(h, rho) < alpha^2 P(h) for h, h+ on a dense premise grid and rho in S_rho."""
    g = paper_gains
    N, (MG,) = g.design_frame()
    nts = g.model.nts
    V = np.linspace(nts.premise_low[0], nts.premise_high[0], 15)
    r = np.linspace(nts.premise_low[1], nts.premise_high[1], 15)
    h = nts.memberships(np.stack(np.meshgrid(V, r, indexing="ij"), axis=-1).reshape(-1, 2))
    P_h = np.einsum("gi,ijk->gjk", h, g.P)
    alpha_sq = g.certificate.decay_rate**2
    worst = -np.inf
    rng = np.random.default_rng(0)
    for rho in np.linspace(-3.0, 3.0, 7):
        N_h = np.einsum("gi,ijk->gjk", h, N) + rho * MG
        for _ in range(3):
            P_next = P_h[rng.permutation(len(h))]
            lhs = np.einsum("gji,gjk,gkl->gil", N_h, P_next, N_h) - alpha_sq * P_h
            worst = max(worst, float(np.linalg.eigvalsh(0.5 * (lhs + lhs.transpose(0, 2, 1))).max()))
    assert worst < 0.0


def test_spectral_radius_on_a_finer_grid_than_the_certificate(paper_gains):
    g = paper_gains
    radius, _, points = spectral_radius_grid(g.model.nts, g.N, g.error_terms(), g.model.dmvt_terms, 81, 13)
    assert points == 81 * 81 * 13
    assert radius < paper_gains.certificate.decay_rate + 1e-9


def test_round_trip_through_json_keeps_the_gains_and_reverifies(paper_gains):
    data = json.loads(json.dumps(paper_gains.to_dict()))
    again = ObserverGains.from_dict(data)
    np.testing.assert_array_equal(again.N, paper_gains.N)
    assert again.version == paper_gains.version


def test_tampered_gains_are_refused(paper_gains):
    data = json.loads(json.dumps(paper_gains.to_dict()))
    data["matrices"]["L"][0][1][0] *= 1.001
    with pytest.raises(VerificationFailed, match="content hash mismatch"):
        ObserverGains.from_dict(data)


def test_verification_rejects_unstable_gains(paper_gains):
    g = paper_gains
    unstable = g.N.copy()
    unstable[:, 1, 1] += 0.2  # pushes the v_y error pole outside the unit circle at high speed
    with pytest.raises(VerificationFailed):
        verify(g.model.nts, g.model.dmvt_terms, g.P, g.R, 1.0, unstable, g.M, g.T)


def test_a_solver_point_that_fails_verification_is_an_error_never_gains(monkeypatch):
    """The solver 'succeeds' but its point is wrong: synthesize raises instead of returning gains."""
    original = Theorem2LMIs.solve

    def corrupted(self, alpha, solver, time_limit_s=60.0):
        solution = original(self, alpha, solver, time_limit_s)
        return dataclasses.replace(solution, H=solution.H * 0.0)

    monkeypatch.setattr(Theorem2LMIs, "solve", corrupted)
    with pytest.raises(VerificationFailed, match="numpy verification"):
        synthesize(
            options=DesignOptions(design="paper", fault_order=1, optimise_decay_rate=False, solvers=("CLARABEL",))
        )


@pytest.mark.parametrize(
    "options",
    [
        DesignOptions(design="paper", fault_order=1, lmi_form="vertex", optimise_decay_rate=False),
        DesignOptions(design="paper", fault_order=2, lyapunov="common", optimise_decay_rate=False),
        DesignOptions(
            design="paper", fault_order=1, solvers=("SCS",), optimise_decay_rate=False, solver_time_limit_s=30.0
        ),
    ],
    ids=["vertex-form", "common-P", "scs-only"],
)
def test_other_forms_and_solvers_are_verified(options):
    g = synthesize(options=options)
    c = g.certificate
    assert c.verified and c.spectral_radius_max < 1.0
    assert c.n_lmis_verified == (32 if options.lyapunov == "fuzzy" else 8)
    assert c.solver == options.solvers[0]


def test_bisection_improves_on_the_stability_design(paper_gains_order1):
    best = synthesize(options=DesignOptions(design="paper", fault_order=1))
    assert best.certificate.decay_rate <= paper_gains_order1.certificate.decay_rate
    assert best.certificate.solves >= 2
