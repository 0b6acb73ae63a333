"""Tolerance analysis and parameter sweeps: Monte Carlo over manufacturing and assembly
errors with compensators, sensitivity, yield, grid sweeps; executed on Dask.

Like :mod:`lfsim.optimize`, this package changes designs and evaluates metrics
(through :mod:`lfsim.design`, :mod:`lfsim.ini` and :mod:`lfsim.analysis`); it
contains no physics.
"""
