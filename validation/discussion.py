"""The study's explanations: what the coverage of our σ says, and why the methods rank as they do.

Every number in these paragraphs comes from the run's summary; the wording follows them
(inside or outside the target band, which method is smaller, ...).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from drivegain.validation.estimators import OURS
from drivegain.validation.markdown import fmt, sigma_word
from drivegain.validation.scenarios import COVERAGE_BAND, Scenario


def coverage_text(
    summary: dict[str, Any], scen: Sequence[Scenario], factor: float, tab: dict[str, Any]
) -> str:
    """What the coverage numbers say about our σ, and why.

    Parameters
    ----------
    summary
        Scenario key → :func:`~drivegain.validation.statistics.scenario_summary`.
    scen
        The scenarios run, in order.
    factor
        Variance factor of the decimated noise
        (:func:`~drivegain.validation.statistics.decimated_noise_factor`).
    tab
        The pipeline run of :func:`~drivegain.validation.paper.pipeline_tables`.
    """
    lines = []
    cov = {sc.key: summary[sc.key]["methods"][OURS] for sc in scen}
    inside = [COVERAGE_BAND[0] <= c["coverage_all"] <= COVERAGE_BAND[1] for c in cov.values()]
    zs = {k: float(np.mean(c["z_std"])) for k, c in cov.items()}
    band = f"{100 * COVERAGE_BAND[0]:.0f}-{100 * COVERAGE_BAND[1]:.0f} %"
    verdict = (
        f"inside the {band} target in every scenario"
        if all(inside)
        else f"**outside the {band} target in "
        + ", ".join(k for k, ok in zip(cov, inside, strict=True) if not ok)
        + "**"
    )
    lines.append(
        "Ours: pooled coverage "
        + ", ".join(f"{100 * c['coverage_all']:.1f} % ({k})" for k, c in cov.items())
        + f": {verdict}; the nominal coverage of ±2σ is 95.4 % (a σ computed as for white "
        f"errors would cover {100 * (2 * _phi(2 / math.sqrt(factor)) - 1):.1f} %). The spread of "
        "z = (ĝ − g)/σ̂, averaged over the joints, is "
        + ", ".join(f"{v:.2f} ({k})" for k, v in zs.items())
        + " (1 for an honest σ): our σ is "
        + "; ".join(f"{sigma_word(v)} in {k}" for k, v in zs.items())
        + "."
    )
    lines.append("")
    acf = tab["truth_error_acf"]
    ls_z = {sc.key: float(np.mean(summary[sc.key]["methods"]["global_ls"]["z_std"])) for sc in scen}
    lines.append(
        "Why a plain σ would not do: the decimated equation errors are not white. The "
        "decimation low-pass keeps noise up to 0.8 of the new Nyquist frequency only, so the "
        "errors are band-limited and correlated between neighbouring samples (autocorrelation "
        "at lags 1, 2, 3: "
        + ", ".join(f"{v:+.2f}" for v in acf)
        + ", mean over joints of the true parameters' equation errors in the run of the "
        "tables), and the regressors live at the trajectory's low frequencies, where the "
        "noise density is higher than that of white noise of the same variance. Measured "
        "here on white noise put through the same decimation and projected on the "
        f"trajectory's harmonics: variance factor {factor:.3f}, so a σ computed as for white "
        f"errors is too small by √{factor:.3f} = {math.sqrt(factor):.3f}. The eq. (10) σ of "
        "the global WLS, which takes the errors as white, has a z spread of "
        + ", ".join(f"{v:.2f} ({k})" for k, v in ls_z.items())
        + " (it is also biased under current noise)."
    )
    lines.append("")
    lines.append(
        "Ours accounts for it: its covariance is built from the whitened errors' "
        "autocovariance over a few lags, corrected for what the fit takes out of the "
        'residuals (docs/model.md, "Standard deviations"); the ablation with the Newey-West '
        "sandwich it used before shows what that changes. Its Case 2 payload parameters "
        "take their covariance from the same error model, the gains' share and its "
        "correlation with the fit included; where that model finds a drive's entries near "
        "its reversals misfit (κ̂ ≥ 1: the drives stick there, as in closed loop, or the "
        "Coulomb sign is uncertain), Case 2 leaves those entries out and takes Newey-West's "
        "sandwich on the entries it keeps, with the gains' covariance (docs/model.md, "
        '"Case 2 without the misfit reversals"). The other methods\' Case 2 use the '
        "Newey-West sandwich plus their gains' covariance. The per-joint LS σ of joint 5 is "
        "too small for another reason: it ignores the uncertainty of ĝ6, which enters joint "
        "5's known column."
    )
    return "\n".join(lines)


def _phi(x: float) -> float:
    """Standard normal cumulative distribution at ``x``."""
    return 0.5 * (1 + math.erf(x / math.sqrt(2)))


def findings_text(summary: dict[str, Any], scen: Sequence[Scenario], tab: dict[str, Any]) -> str:
    """Why the methods rank as they do, from this run's numbers."""
    st = {sc.key: summary[sc.key]["methods"] for sc in scen}
    main = scen[0].key
    c1b = summary[main]["cases"]["case1"]["payload_b_rms_pct"]
    c2b = summary[main]["cases"]["case2"]["payload_b_rms_pct"]
    L = ["## Why: what the comparison shows", ""]
    m = st[main]
    L.append(
        f"1. **Equal torque noise on every joint ({', '.join(sc.key for sc in scen[:2])}).** "
        "Ours, the global WLS with the mass on the right-hand side and the unweighted TLS "
        "with the coupled current matrix give practically the same gains (ratio of their RMS "
        "error to ours: "
        + "; ".join(
            f"{sc.key}: global WLS {st[sc.key]['global_ls']['ratio_to_ours'][0]:.3g}, "
            f"TLS {st[sc.key]['tls']['ratio_to_ours'][0]:.3g}"
            for sc in scen[:2]
        )
        + "). Two reasons: the "
        "simulated torque noise has the same σ on every joint and is small against the "
        "signal, so weighting changes little and LS's errors-in-variables bias is below its "
        "σ. The paper's α criterion is flat on such data (the α chosen wanders over the whole "
        f"grid, {100 * summary[main]['alpha']['at_grid_ends']:.0f} % of seeds at an end); "
        "ours has no weight to choose."
    )
    if len(scen) > 2:
        k3 = scen[2].key
        s3 = st[k3]
        r_tls = s3["tls"]["ratio_to_ours"]
        r_gls = s3["global_ls"]["ratio_to_ours"]
        bias = s3["global_ls"]["bias_pct"]
        L.append(
            f"2. **Unequal, larger noise ({k3}).** Here the row weights (and α) matter: the "
            f"unweighted TLS has {r_tls[0]:.3g} times our RMS error "
            f"[{r_tls[1]:.3g}, {r_tls[2]:.3g}]. The "
            f"global LS is biased by {min(bias):+.2g} to {max(bias):+.2g} % on the gains "
            f"({r_gls[0]:.3g} times our error), with a coverage of "
            f"{100 * s3['global_ls']['coverage_all']:.0f} %: the noisy currents are regressors "
            "in LS, whose errors-in-variables bias shrinks the V coefficients toward zero in "
            "proportion to the noise power. Ours has the currents on the left-hand side of its "
            "model (eq. 21 solved for them), where their noise does no harm."
        )
        pj, cad, ours = s3["per_joint"], s3["ours_cad"], s3[OURS]
        L.append(
            "3. **Per-joint LS (the older approach).** With all 10 payload parameters known it "
            "scales each wrist joint directly, which ours with the mass only cannot: there "
            f"it is better on joints 4-6 in {k3} (RMS "
            f"{', '.join(fmt(v, 2) for v in pj['rmse_pct'][3:])} % against ours "
            f"{', '.join(fmt(v, 2) for v in ours['rmse_pct'][3:])} %). Given the same "
            f"information, ours is better than it on {_count_better(cad, pj)} of 6 joints "
            f"(RMS {', '.join(fmt(v, 2) for v in cad['rmse_pct'])} % against "
            f"{', '.join(fmt(v, 2) for v in pj['rmse_pct'])} %): the global problem shares the "
            "robot's parameters between joints, the per-joint one identifies a scaled copy "
            "per joint. In the equal-noise scenarios it is worse than ours overall "
            f"({m['per_joint']['ratio_to_ours'][0]:.3g} times our error in {main}). With the "
            "mass only it cannot scale joints 4-6 at all, and on a real robot the payload's "
            "CAD values are themselves uncertain."
        )
    L.append(
        f"4. **The coupled wrist.** A diagonal current matrix leaves g6·v6 out of joint 5's "
        f"equation: the unweighted TLS then misses g5 by {m['tls_diag']['rmse_pct'][4]:.3g} % "
        f"and g6 by {m['tls_diag']['rmse_pct'][5]:.3g} % (and, through the shared parameters, "
        f"every other gain by {min(m['tls_diag']['rmse_pct'][:4]):.2g}-"
        f"{max(m['tls_diag']['rmse_pct'][:4]):.2g} %), against "
        f"{m['tls']['rmse_pct'][4]:.2g} % and {m['tls']['rmse_pct'][5]:.2g} % with the coupled "
        "V, whatever the noise: it is a model error, not noise. The payload identified with "
        f"those gains is off by {np.mean(m['tls_diag']['payload_b_rms_pct']):.3g} % on average."
    )
    L.append(
        "5. **Case 1 against Case 2.** The a priori gains are off by up to 24 % of their value "
        "(31 % of the true gain, joint 4); every payload parameter identified with them "
        "inherits an error of "
        f"{min(c1b):.2g}-{max(c1b):.2g} % ({main}, 4.59 kg), which their reported ±2σ cover in "
        f"{100 * float(np.mean(summary[main]['cases']['case1']['payload_b_coverage'])):.0f} % of "
        "the cases (parameters × seeds) only. With our gains the errors fall to the noise level "
        f"({min(c2b):.2g}-{max(c2b):.2g} %), as in the paper's Tables 2 and 5."
    )
    L.append(
        "6. **Limits of this study.** The simulated robot follows the trajectory exactly, its "
        "model is the identification model (no unmodelled friction, flexibility or delay), "
        "the payload's nominal values are its true ones, and the same excitation serves runs "
        "a, b and c. Real data add model errors, which is why the paper's error norms and σ "
        "are ten to a hundred times ours; the ranking of the methods under equal noise says "
        "nothing about that regime, the unequal-noise scenario is closer to it."
    )
    L.append("")
    return "\n".join(L)


def _count_better(a: dict[str, Any], b: dict[str, Any]) -> int:
    """On how many joints method statistics ``a`` have a smaller RMS gain error than ``b``."""
    return int(np.sum(np.asarray(a["rmse_pct"]) < np.asarray(b["rmse_pct"])))
