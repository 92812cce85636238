"""The mathematics of the fault estimator: vehicle model, N-TS fuzzy model, certified observer design.

The method follows the paper [1]_: a 2-DOF vehicle model rewritten as a 4-rule N-TS fuzzy model (eqs. 1-16),
an augmented fault model (eqs. 17-18) and the observer of eq. (19), whose gains come from the LMIs of its
Theorem 2. Everywhere in this code base, "the paper" and the numbers of equations, lemmas, theorems,
algorithms, tables and figures are those of [1]_; docs/math.md maps them onto the modules,
says where the printed text had to be corrected, and where the product goes beyond it (the noise-aware
design, the switched gain sets, the real-vehicle terms and calibration).

Pure mathematics: numpy, scipy and cvxpy, no files, clocks, web or transport.

References
----------
.. [1] S. W., J. P., X. S., L. F. and X. M., "Takagi-Sugeno fuzzy fault estimator design for nonlinear
   dynamics of autonomous ground vehicles". The text the project works from names its authors by these
   initials only (its author contributions) and gives no venue, volume or DOI.
"""
