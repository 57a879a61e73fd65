"""Plain-language diagnoses of a doubtful identification: which current was logged.

IDIM-WTLS finds the gains from the change that the payload makes in the currents. The current
a controller logs as its "target" may be its feed-forward, computed from its own model without
the payload: the payload's effect then is not in that current at all, and the gains come out
as nonsense with huge standard deviations (or no solution). Two symptoms are checked:

- the loaded run's currents do not change with the payload: Case 1 (a priori gains, IDIM-WLS
  of both runs) sees a payload mass not significantly different from zero
  (:data:`MASS_SIGNIFICANCE` standard deviations) or below :data:`MASS_FRACTION` of the nominal
  mass;
- the identified gains are poorly determined (relative standard deviation above
  :data:`GAIN_RSD_DOUBTFUL` %).

Each gives one sentence that says why and suggests the other current channel (``--current``).
"""

from __future__ import annotations

import numpy as np

from drivegain.config.payload import PAYLOAD_PARAMS
from drivegain.identify.procedure import ProcedureResult

#: |m̂| below this many standard deviations: the payload's mass is not seen by the currents.
MASS_SIGNIFICANCE = 3.0
#: |m̂| below this fraction of the nominal mass (with the a priori gains' scale): not seen.
MASS_FRACTION = 0.1
#: Gains with a relative standard deviation above this (%) are called meaningless.
GAIN_RSD_DOUBTFUL = 20.0

_OTHER = {"reference": "measured", "measured": "reference"}


def other_channel_hint(channel: str) -> str:
    """The sentence that suggests the other current channel."""
    other = _OTHER.get(channel, "measured")
    return (
        f"the {channel} current may not contain the payload's effect (a controller's target "
        f"current is often its feed-forward, computed without the payload): try --current "
        f"{other}"
    )


def payload_mass_seen(result: ProcedureResult) -> tuple[bool, float, float, float] | None:
    """Whether Case 1 sees the payload's mass in the loaded run's currents.

    Returns
    -------
    (seen, mass, std, nominal) or None
        kg; None when there is no loaded run or no nominal mass.
    """
    if not result.case1.payloads:
        return None
    p = result.case1.payloads[0]
    i = PAYLOAD_PARAMS.index("M")
    m, s, nominal = float(p.values[i]), float(p.std[i]), float(p.nominal[i])
    if not (np.isfinite(m) and np.isfinite(nominal) and nominal > 0):
        return None
    significant = not np.isfinite(s) or abs(m) > MASS_SIGNIFICANCE * s
    seen = significant and abs(m) >= MASS_FRACTION * nominal
    return seen, m, s, nominal


def current_warnings(result: ProcedureResult, channel: str) -> list[str]:
    """Warnings (plain sentences) when the current channel looks like the wrong one.

    Parameters
    ----------
    result
        The procedure's result.
    channel
        ``reference`` or ``measured``: the current the runs used.
    """
    out: list[str] = []
    seen = payload_mass_seen(result)
    if seen is not None and not seen[0]:
        _, m, s, nominal = seen
        out.append(
            f"the loaded run's currents do not change with the payload: with the a priori gains "
            f"they show a payload mass of {m:.3g} ± {2 * s:.2g} kg (2σ) for the nominal "
            f"{nominal:.4g} kg; " + other_channel_hint(channel)
        )
    if result.wtls is not None and result.gains_std is not None:
        rsd = 100.0 * result.gains_std / np.abs(result.gains)
        worst = float(np.nanmax(rsd)) if rsd.size else 0.0
        if not np.isfinite(worst) or worst > GAIN_RSD_DOUBTFUL:
            why = "see above" if out else other_channel_hint(channel)
            out.append(
                f"the identified gains are meaningless (%σ up to {worst:.3g} %): the data do "
                f"not determine them; {why}"
            )
    return out
