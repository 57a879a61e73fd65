"""The validation study: Monte Carlo comparison of the estimators on simulated robots, the
paper's tables in simulation, and the real TX-40 recording (``benchmarks/validate.py`` runs it
and writes ``docs/validation.md``).

Modules, in the order of the data: :mod:`.scenarios` (noise levels, seeds, budget),
:mod:`.world` (the simulated TX-40, its recordings and random excitations), :mod:`.cell`
(closed-loop recordings by the simulated drives), :mod:`.estimators` (the compared methods, the
Monte Carlo), :mod:`.cluster` (where the seeds run: here, local processes or Dask),
:mod:`.statistics` (bias, spread, coverage, paired ratios), :mod:`.mustshow` (issue 17's targets),
:mod:`.paper` (the paper's tables through the whole pipeline), :mod:`.real` (the real
recording), :mod:`.figures`, :mod:`.markdown`, :mod:`.discussion` and :mod:`.document` (the
page), :mod:`.study` (the driver, :func:`~drivegain.validation.study.run_study`).
"""
