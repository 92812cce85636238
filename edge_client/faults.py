"""Actuator fault injection (eqs. 5-11), validated models with clear errors.

Every fault writes f = add(t) + gain(t) * u_d for one actuator ("torque" or
"steer"), so that a fleet's faults compile into two arrays per channel and the
plant never evaluates Python objects per vehicle:

* ``bias``: a step of ``magnitude`` at ``onset_s`` (eqs. 7-8), optionally
  ramped in over ``ramp_s`` and removed at ``end_s``;
* ``loss_of_effectiveness``: alpha(t) = 1 - beta (t - t_f), floored at
  ``alpha_min`` (eq. 10), f = (alpha(t) - 1) u_d (eq. 11);
* ``sinusoidal``: amplitude sin(omega (t - phase_ref)), repetitive faults;
* ``intermittent``: a bias that is on for ``on_s`` out of every ``period_s``.

Units: torque faults in [N m], steering faults in [rad], times in [s].
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator

from synth.model import FloatArray

Channel = Literal["torque", "steer"]
CHANNEL_INDEX = {"torque": 0, "steer": 1}
Finite = Annotated[float, Field(allow_inf_nan=False)]
NonNegative = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]


class _Fault(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    channel: Channel = Field(description="which actuator: 'torque' (T_f) or 'steer' (delta_f)")
    onset_s: NonNegative = Field(0.0, description="fault onset t_f [s]")
    end_s: NonNegative | None = Field(None, description="when the fault disappears [s]; None = never")

    @model_validator(mode="after")
    def _end_after_onset(self) -> _Fault:
        if self.end_s is not None and self.end_s <= self.onset_s:
            raise ValueError(f"end_s must be after onset_s, got end_s={self.end_s} <= onset_s={self.onset_s}")
        return self

    def active(self, t: FloatArray) -> NDArray[np.bool_]:
        on = t >= self.onset_s
        if self.end_s is not None:
            on &= t < self.end_s
        return on

    def additive(self, t: FloatArray) -> FloatArray:
        """The part of f independent of u_d, shape of t."""
        return np.zeros_like(t)

    def multiplicative(self, t: FloatArray) -> FloatArray:
        """gain(t) with f = gain(t) * u_d, shape of t."""
        return np.zeros_like(t)


class BiasFault(_Fault):
    """A constant bias added to the demanded input (eqs. 7-8)."""

    kind: Literal["bias"] = "bias"
    magnitude: Finite = Field(description="bias [N m] for torque, [rad] for steer")
    ramp_s: NonNegative = Field(0.0, description="time to reach the full bias [s]; 0 = a step")

    def additive(self, t: FloatArray) -> FloatArray:
        elapsed = t - self.onset_s
        shape = np.ones_like(t) if self.ramp_s == 0 else np.clip(elapsed / self.ramp_s, 0.0, 1.0)
        return np.where(self.active(t), self.magnitude * shape, 0.0)


class LossOfEffectivenessFault(_Fault):
    """Actuator effectiveness alpha(t) = max(1 - beta (t - t_f), alpha_min) (eqs. 9-11)."""

    kind: Literal["loss_of_effectiveness"] = "loss_of_effectiveness"
    rate_per_s: Positive = Field(description="degradation rate beta [1/s]")
    alpha_min: Annotated[float, Field(ge=0, lt=1)] = Field(description="final effectiveness alpha_min [-]")

    def multiplicative(self, t: FloatArray) -> FloatArray:
        alpha = np.maximum(1.0 - self.rate_per_s * (t - self.onset_s), self.alpha_min)
        # eq. (11): f = (alpha(t) - 1) u_d
        return np.where(self.active(t), alpha - 1.0, 0.0)


class SinusoidalFault(_Fault):
    """A repetitive fault amplitude * sin(omega (t - onset))."""

    kind: Literal["sinusoidal"] = "sinusoidal"
    amplitude: Finite = Field(description="amplitude [N m] or [rad]")
    omega_radps: Positive = Field(description="angular frequency [rad/s]")
    offset: Finite = Field(0.0, description="constant part added while active")
    phase_from_zero: bool = Field(
        False, description="measure the phase from t = 0 instead of from the onset (the paper's Scenario 1)"
    )

    def additive(self, t: FloatArray) -> FloatArray:
        t_ref = t if self.phase_from_zero else t - self.onset_s
        return np.where(self.active(t), self.amplitude * np.sin(self.omega_radps * t_ref) + self.offset, 0.0)


class IntermittentFault(_Fault):
    """A bias of ``magnitude`` present for ``on_s`` out of every ``period_s``."""

    kind: Literal["intermittent"] = "intermittent"
    magnitude: Finite = Field(description="bias while on [N m] or [rad]")
    period_s: Positive = Field(description="repetition period [s]")
    on_s: Positive = Field(description="on-time per period [s]")

    @model_validator(mode="after")
    def _on_within_period(self) -> IntermittentFault:
        if self.on_s >= self.period_s:
            raise ValueError(f"on_s must be shorter than period_s, got on_s={self.on_s} >= period_s={self.period_s}")
        return self

    def additive(self, t: FloatArray) -> FloatArray:
        phase = np.mod(t - self.onset_s, self.period_s)
        return np.where(self.active(t) & (phase < self.on_s), self.magnitude, 0.0)


Fault = Annotated[
    BiasFault | LossOfEffectivenessFault | SinusoidalFault | IntermittentFault,
    Field(discriminator="kind"),
]


def fault_tables(faults: list[Fault] | tuple[Fault, ...], t: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Compile faults to (add, gain), each of shape (len(t), 2): f = add + gain * u_d."""
    add = np.zeros((t.size, 2))
    gain = np.zeros((t.size, 2))
    for fault in faults:
        k = CHANNEL_INDEX[fault.channel]
        add[:, k] += fault.additive(t)
        gain[:, k] += fault.multiplicative(t)
    return add, gain
