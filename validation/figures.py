"""The study's figures: small PNGs for docs/validation.md (matplotlib, Agg backend).

A method has the same colour in every figure; ablations are hatched.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from drivegain.config.payload import PAYLOAD_PARAMS
from drivegain.validation.estimators import METHODS, OURS, Method, SeedResult
from drivegain.validation.scenarios import COVERAGE_BAND, SCENARIOS
from drivegain.validation.statistics import z_scores
from drivegain.validation.world import World


def _plt() -> Any:
    # Imported on first use: the Monte Carlo does not need matplotlib, and Agg needs no display.
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _color(m: Method) -> str:
    """The same colour for a method in every figure."""
    return f"C{[x.key for x in METHODS].index(m.key)}"


def figure_gain_errors(summary: dict[str, Any], joint_names: Sequence[str], path: Path) -> None:
    """RMS relative gain error (%) per joint and method, one panel per scenario (log scale).

    ``summary`` maps scenario keys to :func:`~drivegain.validation.statistics.scenario_summary`.
    """
    plt = _plt()
    scen = [sc for sc in SCENARIOS if sc.key in summary]
    fig, axes = plt.subplots(len(scen), 1, figsize=(8, 2.4 * len(scen)), sharex=True, squeeze=False)
    n = len(joint_names)
    width = 0.8 / len(METHODS)
    for ax, sc in zip(axes[:, 0], scen, strict=True):
        stats = summary[sc.key]["methods"]
        for i, m in enumerate(METHODS):
            if m.key not in stats or stats[m.key]["seeds"] == 0:
                continue
            x = np.arange(n) + (i - (len(METHODS) - 1) / 2) * width
            _method_bars(ax, m, x, stats[m.key]["rmse_pct"], width)
        ax.set_yscale("log")
        ax.set_ylabel("RMS error %")
        ax.set_title(f"{sc.label} ({summary[sc.key]['seeds']} seeds)", fontsize=9)
        ax.grid(alpha=0.3, axis="y", which="both")
    axes[-1, 0].set_xticks(np.arange(n), list(joint_names))
    axes[0, 0].legend(fontsize=6.5, ncol=3, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def _method_bars(ax: Any, m: Method, x: np.ndarray, values: Any, width: float) -> None:
    """One method's bars, in its colour (ablations hatched), labelled for the legend."""
    ax.bar(
        x,
        values,
        width,
        color=_color(m),
        label=m.label,
        hatch="//" if m.ablation else None,
        edgecolor="white",
        linewidth=0.3,
    )


def figure_coverage(
    summary: dict[str, Any], results: dict[str, list[SeedResult]], world: World, path: Path
) -> None:
    """Left: coverage (%) of ±2σ per joint for the methods reporting σ. Right: z of ours."""
    plt = _plt()
    scen = [sc for sc in SCENARIOS if sc.key in summary]
    fig, axes = plt.subplots(
        len(scen),
        2,
        figsize=(9, 2.3 * len(scen)),
        squeeze=False,
        gridspec_kw={"width_ratios": [3, 2]},
    )
    with_std = [m for m in METHODS if m.reports_std]
    n = world.robot.n
    width = 0.8 / len(with_std)
    g = world.truth.gains
    for row, sc in enumerate(scen):
        ax = axes[row, 0]
        stats = summary[sc.key]["methods"]
        ax.axhspan(COVERAGE_BAND[0] * 100, COVERAGE_BAND[1] * 100, color="0.9")
        ax.axhline(95.45, color="k", lw=0.6, ls=":")
        for i, m in enumerate(with_std):
            x = np.arange(n) + (i - (len(with_std) - 1) / 2) * width
            _method_bars(ax, m, x, 100 * np.asarray(stats[m.key]["coverage"]), width)
        ax.set_ylim(0, 105)
        ax.set_xticks(np.arange(n), world.robot.joint_names)
        ax.set_ylabel("truth in ±2σ %")
        ax.set_title(sc.label, fontsize=9)
        ax2 = axes[row, 1]
        z = z_scores(results[sc.key], OURS, g).ravel()
        ax2.hist(
            z,
            bins=np.linspace(-5, 5, 41),
            density=True,
            color="C0",
            alpha=0.7,
            label="ours: (ĝ−g)/σ̂",
        )
        u = np.linspace(-5, 5, 201)
        ax2.plot(u, np.exp(-u * u / 2) / math.sqrt(2 * math.pi), "k", lw=0.8, label="N(0, 1)")
        ax2.set_title(f"z of ours, std {z.std():.2f}", fontsize=9)
        if row == 0:
            ax2.legend(fontsize=6.5)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", ncol=len(with_std), fontsize=7)
    fig.tight_layout(rect=(0, 0, 1, 0.96))
    fig.savefig(path, dpi=80)
    plt.close(fig)


def figure_torques(res: Any, world: World, path: Path) -> None:
    """The paper's Fig. 3: measured (V·ĝ) and computed (W·χ̂) torques (N·m) of run b, Case 2.

    ``res`` is the identification result of :func:`drivegain.identify.pipeline.run_identify`.
    """
    plt = _plt()
    d = res.designs["loaded"]
    case = res.case2
    y = d.torque(case.gains)
    yh = d.model_torque(case.base, case.payloads[0].values)
    t = d.run.t
    n = y.shape[1]
    fig, axes = plt.subplots(n, 1, figsize=(8, 1.2 * n), sharex=True, squeeze=False)
    for j, ax in enumerate(axes[:, 0]):
        ax.plot(t, y[:, j], lw=1.4, color="C0", label="measured V·ĝ")
        ax.plot(t, yh[:, j], lw=0.8, ls="--", color="k", label="computed W·χ̂")
        ax.set_ylabel(f"{world.robot.joint_names[j]} N·m", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7, loc="upper right", ncol=2)
    axes[0, 0].set_title(
        "Run b (4.59 kg payload), Case 2 gains: measured and computed torques", fontsize=9
    )
    axes[-1, 0].set_xlabel("time s", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=70)
    plt.close(fig)


def figure_payload(summary: dict[str, Any], scenario: str, path: Path) -> None:
    """RMS relative payload errors (%), Case 1 (a priori gains) vs Case 2 (identified gains)."""
    plt = _plt()
    cases = summary[scenario]["cases"]
    fig, axes = plt.subplots(1, 2, figsize=(9, 2.8), sharey=True)
    x = np.arange(len(PAYLOAD_PARAMS))
    for ax, which, title in (
        (axes[0], "b", "payload 4.59 kg (Table 2)"),
        (axes[1], "c", "payload 1.686 kg (Table 5)"),
    ):
        ax.bar(
            x - 0.2, cases["case1"][f"payload_{which}_rms_pct"], 0.4, label="Case 1: a priori gains"
        )
        ax.bar(
            x + 0.2,
            cases["case2"][f"payload_{which}_rms_pct"],
            0.4,
            label="Case 2: identified gains",
        )
        ax.set_yscale("log")
        ax.set_xticks(x, list(PAYLOAD_PARAMS), fontsize=7)
        ax.set_title(title, fontsize=9)
        ax.grid(alpha=0.3, axis="y", which="both")
    axes[0].set_ylabel("RMS error % of truth")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
