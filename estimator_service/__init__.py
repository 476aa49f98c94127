"""estimator_service: GP regression, GP-BayesFilters and the zenoh estimator process.

This package never imports :mod:`gpbf_env`: it works on any robot's recorded data.
"""
