import numpy as np
import pytest
from pydantic import TypeAdapter, ValidationError

from edge_client.faults import (
    BiasFault,
    Fault,
    IntermittentFault,
    LossOfEffectivenessFault,
    SinusoidalFault,
    fault_tables,
)
from tests.tolerances import LAST_BITS_ATOL

T = np.arange(0, 20, 0.01)


def test_bias_is_a_heaviside_step_eqs_7_8():
    f = BiasFault(channel="torque", onset_s=5.0, magnitude=30.0)
    add, gain = fault_tables([f], T)
    np.testing.assert_array_equal(add[:, 0], 30.0 * (T >= 5.0))
    assert not add[:, 1].any() and not gain.any()


def test_loss_of_effectiveness_follows_eqs_9_11():
    f = LossOfEffectivenessFault(channel="torque", onset_s=4.0, rate_per_s=0.02, alpha_min=0.7)
    add, gain = fault_tables([f], T)
    alpha = np.where(T >= 4.0, np.maximum(1 - 0.02 * (T - 4.0), 0.7), 1.0)
    np.testing.assert_allclose(gain[:, 0], alpha - 1.0, atol=LAST_BITS_ATOL)
    u_d = 200.0
    assert (add[:, 0] + gain[:, 0] * u_d)[T >= 19.0].min() == pytest.approx(-0.3 * u_d)


def test_sinusoidal_and_intermittent_signals():
    s = SinusoidalFault(channel="steer", amplitude=0.1, omega_radps=0.5, onset_s=2.0)
    add, _ = fault_tables([s], T)
    np.testing.assert_allclose(add[:, 1], np.where(T >= 2.0, 0.1 * np.sin(0.5 * (T - 2.0)), 0.0), atol=LAST_BITS_ATOL)
    i = IntermittentFault(channel="steer", magnitude=0.02, period_s=4.0, on_s=1.0, onset_s=2.0)
    add, _ = fault_tables([i], T)
    on = (T >= 2.0) & (np.mod(T - 2.0, 4.0) < 1.0)
    np.testing.assert_array_equal(add[:, 1], np.where(on, 0.02, 0.0))


def test_fault_ends_at_end_s():
    f = BiasFault(channel="steer", onset_s=1.0, end_s=3.0, magnitude=0.05)
    add, _ = fault_tables([f], T)
    assert add[(T >= 1.0) & (T < 3.0), 1].min() == 0.05 and not add[T >= 3.0, 1].any()


@pytest.mark.parametrize(
    ("data", "field"),
    [
        ({"kind": "bias", "channel": "brake", "magnitude": 1.0}, "channel"),
        ({"kind": "loss_of_effectiveness", "channel": "torque", "rate_per_s": -1, "alpha_min": 0.5}, "rate_per_s"),
        ({"kind": "intermittent", "channel": "steer", "magnitude": 1, "period_s": 1, "on_s": 2}, "on_s"),
        ({"kind": "bias", "channel": "torque", "magnitude": 1, "onset_s": 5, "end_s": 2}, "end_s"),
        ({"kind": "wobble", "channel": "torque"}, "wobble"),
    ],
)
def test_invalid_faults_name_the_field(data, field):
    with pytest.raises(ValidationError) as info:
        TypeAdapter(Fault).validate_python(data)
    assert field in str(info.value)
