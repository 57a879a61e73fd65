"""The validation study: Monte Carlo comparison of the estimators on simulated robots, the
paper's tables in simulation, and the real TX-40 recording (``benchmarks/validate.py`` runs it
and writes ``docs/validation.md``)."""
