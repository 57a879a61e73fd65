"""Physical plausibility of an identification: friction and rotor inertias must be positive.

Only parameters identified on their own are judged: a regrouped base parameter (name ending in
``R``) mixes several standard parameters and may have either sign.
"""

from __future__ import annotations

from dataclasses import dataclass

from drivegain.identify.cases import CaseResult


@dataclass(frozen=True)
class Check:
    """Physical plausibility of one identified parameter (friction, rotor inertia > 0).

    Attributes
    ----------
    name
        Base parameter name.
    value, std
        Identified value and its standard deviation (SI unit of the parameter).
    ok
        Whether the value is positive.
    note
        Why it is not, empty when it is.
    """

    name: str
    value: float
    std: float
    ok: bool
    note: str


#: Parameters that must be positive when they are base parameters of their own (not regrouped).
_POSITIVE_PREFIXES = ("Ia", "Fv", "Fc", "fvm", "fcm")


def physical_checks(case: CaseResult) -> list[Check]:
    """Friction coefficients and rotor inertias identified alone must be positive.

    Parameters
    ----------
    case
        An IDIM-WLS identification.

    Returns
    -------
    list of Check
        One per friction or rotor-inertia base parameter that is not regrouped.
    """
    out = []
    for name, v, s in zip(case.base_names, case.base, case.base_std, strict=True):
        if not name.startswith(_POSITIVE_PREFIXES) or name.endswith("R"):
            continue
        if v > 0:
            ok, note = True, ""
        elif v + 2 * s > 0:
            ok, note = False, "not positive, but within 2σ of zero"
        else:
            ok, note = False, "negative beyond 2σ: model or data problem"
        out.append(Check(name=name, value=float(v), std=float(s), ok=ok, note=note))
    return out
