"""Design options: which observer to synthesise and how.

A frozen pydantic model so that profiles, JSON files and REST bodies validate
it the same way; :func:`synth.design.synthesize` receives it read-only.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field

DesignName = Literal["paper", "paper-decoupled", "robust"]
SolverName = Literal["CLARABEL", "SCS"]


class DesignOptions(BaseModel):
    """Options of an observer design.

    ``paper``: Theorem 2 without exact decoupling (wind as a bounded
    disturbance), stability with the best certified decay rate.
    ``paper-decoupled``: Theorem 2 as printed, M D_bar = 0; impossible for
    this plant, refused with the reason before any solve.
    ``robust``: the noise-aware guaranteed-cost design (synth.robust).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    design: DesignName = Field("paper", description="which design to run")
    fault_order: Literal[1, 2, 3] = Field(
        3, description="order q of the fault model (z - 1)^q; 3 is the paper's triple integrator (eq. 17)"
    )
    lyapunov: Literal["fuzzy", "common"] = Field(
        "fuzzy", description="fuzzy P(h) = sum h_i P_i (32 vertex LMIs) or one common P (8 vertex LMIs)"
    )
    lmi_form: Literal["petersen", "vertex"] = Field(
        "petersen",
        description="'vertex': the paper's LMIs at both rho vertices; 'petersen': the equivalent, "
        "smaller form with one multiplier per (i, j)",
    )
    optimise_decay_rate: bool = Field(True, description="bisect on alpha for the best certified decay rate")
    decay_rate_tolerance: Annotated[float, Field(gt=0, lt=0.5)] = Field(
        2e-3, description="width of the final bisection bracket on alpha"
    )
    margin: Annotated[float, Field(gt=0, lt=1)] = Field(
        1e-5, description="strictness margin of every LMI (P_i <= I normalises the scale)"
    )
    solvers: tuple[SolverName, ...] = Field(("CLARABEL", "SCS"), min_length=1, description="fallback chain")
    solver_time_limit_s: Annotated[float, Field(gt=0, le=3600)] = Field(
        60.0, description="wall-clock limit of one solver call [s]"
    )
    torque_fault_scale: Annotated[float, Field(gt=0, allow_inf_nan=False)] = Field(
        1e4, description="torque-fault unit in the solver's coordinates [N m]"
    )
    difference_coordinates: bool = Field(True, description="solve with the fault chain in difference coordinates")
    check_existence: bool = Field(True, description="refuse impossible designs before solving")

    @property
    def decoupled(self) -> bool:
        return self.design == "paper-decoupled"
