"""The files every stage shares, each with one reader and one writer.

- :mod:`.fourier`: the finite Fourier series of an excitation (contracts §6);
- :mod:`.trajectory`: the ``TRAJ.json`` file (contracts §6);
- :mod:`.log`, :mod:`.logwriter`, :mod:`.logreader`: the MCAP acquisition log (contracts §4):
  what writer and reader share, the writer, the reader.
"""
