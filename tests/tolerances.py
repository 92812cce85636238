"""Every numerical tolerance of the test suite, named in one place."""

#: N-TS / 8-rule TS model against the Euler step of eqs. (1)-(2), absolute [state units].
MODEL_EQUALITY_ATOL = 1e-12
#: Membership functions sum to one.
SIMPLEX_ATOL = 1e-12
#: One RK4 step of the plant against a tight reference integration.
PLANT_STEP_ATOL = 1e-9
#: Fault estimate RMSE after 3 s on noise-free paper scenarios, fraction of the fault amplitude.
CONVERGENCE_FRACTION = 0.10
#: A batch step equals the same vehicles stepped one at a time.
BATCH_EQUALITY_ATOL = 1e-9
