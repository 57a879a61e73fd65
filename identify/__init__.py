"""Offline identification: robot model, regressors, base parameters, estimators, reports."""
