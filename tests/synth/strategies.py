"""Hypothesis strategies: states, inputs and premises inside the design domain S_x."""

from hypothesis import strategies as st

finite = {"allow_nan": False, "allow_infinity": False}
speed = st.floats(5.0, 30.0, **finite)
lateral = st.floats(-1.5, 1.5, **finite)
yaw = st.floats(-0.55, 0.55, **finite)
torque = st.floats(-2000.0, 2000.0, **finite)
steer = st.floats(-0.2, 0.2, **finite)
wind = st.floats(-1500.0, 1500.0, **finite)
torque_fault = st.floats(-300.0, 300.0, **finite)
steer_fault = st.floats(-0.1, 0.1, **finite)
