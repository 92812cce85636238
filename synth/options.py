"""Design options: which observer to synthesise and how.

A frozen pydantic model so that profiles, JSON files and REST bodies validate
it the same way; :func:`synth.design.synthesize` receives it read-only.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

DesignName = Literal["paper", "paper-decoupled", "robust"]
SolverName = Literal["CLARABEL", "SCS"]


class NoiseModel(BaseModel):
    """What the noise-aware ('robust') design and the EKF assume about the real world.

    The sensor sigmas are those of the measured y = [v_x, r]; the wind is a
    lateral force treated as white noise of this RMS; the fault rates are RMS
    rates of change of the faults, which set the tracking bandwidth (faster =
    quicker detection, noisier estimates); the scales weight the two fault
    channels in the cost (an error of one scale unit on either channel costs
    the same).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    vx_sigma_mps: Annotated[float, Field(gt=0, le=10, allow_inf_nan=False)] = Field(
        0.05, description="standard deviation of the v_x measurement noise [m/s]"
    )
    r_sigma_radps: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = Field(
        0.005, description="standard deviation of the yaw-rate measurement noise [rad/s]"
    )
    wind_sigma_n: Annotated[float, Field(ge=0, le=1e5, allow_inf_nan=False)] = Field(
        300.0, description="RMS of the lateral wind force, treated as white noise [N]"
    )
    torque_fault_rate_nm_per_s: Annotated[float, Field(gt=0, le=1e5, allow_inf_nan=False)] = Field(
        50.0, description="RMS rate of change of the torque fault [N m/s]"
    )
    steer_fault_rate_rad_per_s: Annotated[float, Field(gt=0, le=10, allow_inf_nan=False)] = Field(
        0.02, description="RMS rate of change of the steering fault [rad/s]"
    )
    torque_fault_scale_nm: Annotated[float, Field(gt=0, allow_inf_nan=False)] = Field(
        10.0, description="torque-fault error that costs one unit [N m]"
    )
    steer_fault_scale_rad: Annotated[float, Field(gt=0, allow_inf_nan=False)] = Field(
        0.005, description="steering-fault error that costs one unit [rad]"
    )


class EffectivenessOptions(BaseModel):
    """The loss-of-effectiveness stage (synth.effectiveness): f = b + (alpha - 1) u per actuator.

    A Kalman filter on the observer's reported faults; it does not change the observer or its gains, so these
    options are not part of the design (changing them needs no resynthesis).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    enabled: bool = Field(False, description="estimate each actuator's effectiveness alpha beside its bias")
    torque_sigma_nm: Annotated[float, Field(gt=0, le=1e5, allow_inf_nan=False)] = Field(
        10.0, description="RMS of the healthy T_f estimate: the stage's measurement noise [N m] (calibration sets it)"
    )
    steer_sigma_rad: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = Field(
        0.0005, description="RMS of the healthy delta_f estimate [rad] (calibration sets it)"
    )
    bias_drift_share: Annotated[float, Field(gt=0, le=100, allow_inf_nan=False)] = Field(
        0.1, description="per-sample standard deviation of the bias's random walk, as a share of the sigma [-]"
    )
    effectiveness_rate_per_sqrt_s: Annotated[float, Field(gt=0, le=10, allow_inf_nan=False)] = Field(
        0.02, description="standard deviation of alpha's random walk over one second [1/sqrt(s)]"
    )
    initial_alpha_sigma: Annotated[float, Field(gt=0, le=10, allow_inf_nan=False)] = Field(
        0.05, description="standard deviation of alpha when the stage starts (at 1) [-]"
    )
    alpha_bounds: tuple[float, float] = Field((0.0, 1.5), description="alpha_hat is kept within these [-]")
    start_after_s: Annotated[float, Field(ge=0, le=3600, allow_inf_nan=False)] = Field(
        3.0, description="the stage starts once the observer has converged, this long after it starts [s]"
    )
    torque_jump_nm: Annotated[float, Field(ge=0, le=1e5, allow_inf_nan=False)] = Field(
        0.0,
        description="standard deviation of a step of the torque bias (a gust's step of the estimate): steps are "
        "detected and attributed to the bias or to alpha (docs/math.md section 14); 0: the bias only drifts, no "
        "jump test on T_f (calibration sets it) [N m]",
    )
    steer_jump_rad: Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)] = Field(
        0.0025,
        description="standard deviation of a step of the steering bias: half the step a strong lateral gust makes "
        "in the delta_f estimate (calibration sets it from the stated gust); 0: no jump test on delta_f [rad]",
    )
    jump_false_alarm_interval_s: Annotated[float, Field(ge=1, le=1e7, allow_inf_nan=False)] = Field(
        600.0,
        description="the jump test's design: its mean time between detections on white innovations, per "
        "channel (sets the CUSUM's threshold) [s]",
    )
    jump_window_s: Annotated[float, Field(gt=0, le=10, allow_inf_nan=False)] = Field(
        0.3,
        description="after a detected step the bias follows the estimate this long (about the observer's "
        "response to a fault step) before the step is attributed to the bias or to alpha [s]",
    )
    jump_loss_prior: Annotated[float, Field(gt=0, lt=1, allow_inf_nan=False)] = Field(
        0.01, description="prior probability that a detected step is a loss of effectiveness, not a bias step [-]"
    )

    @field_validator("alpha_bounds")
    @classmethod
    def _bounds_ordered(cls, bounds: tuple[float, float]) -> tuple[float, float]:
        low, high = bounds
        if not (0.0 <= low < 1.0 < high <= 10.0):
            raise ValueError(f"must satisfy 0 <= low < 1 < high <= 10, got {bounds}")
        return bounds


class SwitchingRule(BaseModel):
    """When a switched robust design uses its fast gain set instead of its quiet one.

    The statistic is an exponentially weighted mean of the innovation energy,
    s_k = forgetting * s_{k-1} + (1 - forgetting) * |nu_k|^2 / 2, with nu_k the
    innovation y_k - C x_hat_k divided by the sensor sigmas (so s is about 1 when
    the estimate is settled and the noise model is right). The fast set runs for
    the first ``start_s`` after every (re)start and for ``hold_s`` after each
    sample with s_k above ``threshold``; the quiet set otherwise. Both sets share
    one Lyapunov function, so any switching sequence keeps the certified decay
    rate (docs/switched-gains.md).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    threshold: Annotated[float, Field(gt=0, le=1e6, allow_inf_nan=False)] = Field(
        4.0, description="innovation statistic above which the fast set is used [dimensionless; 1 = noise level]"
    )
    forgetting: Annotated[float, Field(gt=0, lt=1, allow_inf_nan=False)] = Field(
        0.95, description="forgetting factor of the innovation statistic, per sample"
    )
    hold_s: Annotated[float, Field(ge=0, le=3600, allow_inf_nan=False)] = Field(
        1.0, description="how long the fast set stays on after the statistic exceeded the threshold [s]"
    )
    start_s: Annotated[float, Field(ge=0, le=3600, allow_inf_nan=False)] = Field(
        4.0, description="how long the fast set runs after an observer (re)starts [s]"
    )


#: Certified decay rate per sample of the robust design with one gain set, and of a switched design's sets
#: (the default).
#: One set at 0.994 lets more sensor noise into the estimates than at 0.995; a switched design runs its fast
#: set only at a start and after large innovations, and at 0.994 it clears the paper's wrong initial state
#: sooner (docs/benchmarks/accuracy.md).
ROBUST_DECAY_RATE = 0.995
SWITCHED_DECAY_RATE = 0.994


class DesignOptions(BaseModel):
    """Options of an observer design.

    ``robust`` (default): the noise-aware guaranteed-cost design (synth.robust), by default with two gain
    sets switched at run time (``switching``; null for one set).
    ``paper``: Theorem 2 without exact decoupling (wind as a bounded
    disturbance), stability with the best certified decay rate.
    ``paper-decoupled``: Theorem 2 as printed, M D_bar = 0; impossible for
    this plant, refused with the reason before any solve.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    design: DesignName = Field("robust", description="which design to run")
    fault_order: Literal[1, 2, 3] = Field(
        3,
        description="order q of the fault model (z - 1)^q; 3 is the paper's triple integrator (eq. 17). "
        "Default: 3 for the paper's designs, 1 for 'robust'",
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
    noise: NoiseModel = Field(default_factory=NoiseModel, description="noise assumptions of the 'robust' design")
    robust_decay_rate: Annotated[float, Field(gt=0, lt=1)] = Field(
        ROBUST_DECAY_RATE,
        description="decay rate the 'robust' design must certify on top of its cost (0.995 per 10 ms "
        "sample = a 2 s time constant); with switching, 0.994 unless set (the fast set runs only at a start "
        "and after large innovations, so it can be faster: docs/switched-gains.md)",
    )
    robust_cost: Literal["joint", "h2"] = Field(
        "joint",
        description="how the 'robust' design bounds its cost. 'joint' (default): one LMI per rule pair certifies "
        "both the cost and the decay rate; its bound adds (1 - robust_decay_rate^2) E[e^T P e], which penalises "
        "slow error modes, so faults are tracked faster and with more noise than by a Kalman filter. 'h2': the "
        "H2 cost bounded on its own (rate 1) and the decay rate certified by separate LMIs; steady-state noise "
        "close to the Kalman filter's, slower transients (docs/math.md, section 10)",
    )

    switching: SwitchingRule | None = Field(
        None,
        description="'robust' design with the 'joint' cost only: a fast gain set (the one-set design) and a quiet "
        "one (the 'h2' cost form) under one Lyapunov function, switched at run time by this rule. The default "
        "for that design is the rule's defaults; null: one gain set. Any other design has one gain set",
    )

    @model_validator(mode="after")
    def _switching_defaults(self) -> DesignOptions:
        """The robust design with the 'joint' cost switches between two gain sets unless ``switching`` is given
        (null: one set); a switched design's fast set defaults to a faster certified rate than one gain set.
        Defaults are filled in without marking the fields as set, so a stored profile that left them out keeps
        following them (``model_dump(exclude_unset=True)``)."""
        given = self.model_fields_set
        if "switching" not in given and self.design == "robust" and self.robust_cost == "joint":
            self.__dict__["switching"] = SwitchingRule()
        if self.switching is not None and "robust_decay_rate" not in given:
            self.__dict__["robust_decay_rate"] = SWITCHED_DECAY_RATE
        if self.switching is not None and (self.design != "robust" or self.robust_cost != "joint"):
            raise ValueError(
                "switching needs design='robust' with robust_cost='joint' (the fast set); "
                f"got design={self.design!r}, robust_cost={self.robust_cost!r}"
            )
        return self

    @model_validator(mode="before")
    @classmethod
    def _default_fault_order(cls, data: Any) -> Any:
        """The paper's designs use its triple integrator; the robust design a random walk."""
        if isinstance(data, dict) and "fault_order" not in data:
            return {**data, "fault_order": 1 if data.get("design", "robust") == "robust" else 3}
        return data

    @property
    def decoupled(self) -> bool:
        return self.design == "paper-decoupled"
