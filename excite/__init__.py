"""Excitation trajectories: Fourier series optimised for identification, ruckig approach/retreat.

Modules:

- :mod:`.fourier`: the finite Fourier series (contracts §6), its basis and analytic bounds;
- :mod:`.limits`: working limits (margins), sample checks, rigorous limit usage of a series;
- :mod:`.criteria`: cond / log-det of the base observation matrix and the WTLS criterion, with
  gradients;
- :mod:`.optimise`: SLSQP multi-start with a seed and a budget;
- :mod:`.motion`: ruckig approach and retreat, :class:`~.motion.Motion` sampling, stops;
- :mod:`.trajectory`: the ``TRAJ.json`` file and the motion API re-exported;
- :mod:`.evaluate`, :mod:`.plot`, :mod:`.commands`: metrics, PNG, ``drivegain excite``.
"""
