"""Every numerical tolerance of the test suite, named in one place."""

#: N-TS / 8-rule TS model against the Euler step of eqs. (1)-(2), absolute [state units].
MODEL_EQUALITY_ATOL = 1e-12
#: Membership functions sum to one.
SIMPLEX_ATOL = 1e-12
#: One RK4 step of the plant against a tight reference integration.
PLANT_STEP_ATOL = 1e-9
#: Fault estimate RMSE after 3 s on noise-free paper scenarios, fraction of the fault amplitude.
CONVERGENCE_FRACTION = 0.10
#: The 'h2' cost form against the Kalman filter of the same model at a frozen premise (measured: 1.01).
FROZEN_H2_FORM_COST_RTOL = 1.03
#: A batch step equals the same vehicles stepped one at a time.
BATCH_EQUALITY_ATOL = 1e-9

# -- edge client --------------------------------------------------------------------------------
#: Linearised steady-state lateral response against a long nonlinear plant run, relative.
STEADY_STATE_RTOL = 0.02
#: Latest a fault alarm may arrive after the onset [s] (loss of effectiveness ramps in over seconds).
MAX_ALARM_DELAY_S = 8.0
#: Samples per vehicle that may vanish without error when a router dies (put before zenoh notices).
SILENT_LOSS_PER_VEHICLE = 30
