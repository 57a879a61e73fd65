"""Defaults of the excitation's Fourier series (contracts §6), shared by excite and identify."""

from __future__ import annotations

#: Harmonics per joint of the Fourier series (``drivegain excite --harmonics``): enough to
#: excite the TX-40's base parameters at a ~0.1 Hz base frequency within its limits.
DEFAULT_HARMONICS = 5
#: Base frequency of the series, Hz: a 10 s period, slow enough for large motions of the arm.
DEFAULT_BASE_FREQUENCY_HZ = 0.1
#: Periods an excitation runs (the first and last are trimmed by the filters' borders).
DEFAULT_PERIODS = 3
