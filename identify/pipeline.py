"""``drivegain identify``: logs in, drive gains, dynamic parameters and reports out.

Reads the runs (:mod:`.logformat`), filters and decimates them (:mod:`.prepare`), runs the
paper's procedure (:mod:`.procedure`) and writes ``report.json``, ``report.md``,
``report.html`` and the plots.
Everything is written into a temporary folder beside ``--out`` and moved into place only when
complete: a failure leaves ``--out`` untouched.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from drivegain.config.payload import Payload, load_payload
from drivegain.config.robot import Robot, WristFriction, load_robot
from drivegain.dynamics.model import build_model
from drivegain.errors import IdentificationError, InputError
from drivegain.identify import consistent_report as cr
from drivegain.identify import prepchoice
from drivegain.identify.blas import limited_blas_threads
from drivegain.identify.bootstrap import MIN_REPLICATES
from drivegain.identify.diagnose import current_warnings, other_channel_hint
from drivegain.identify.gains import Estimator
from drivegain.identify.loading import load_and_prepare
from drivegain.identify.maskgate import MASK_AUTO
from drivegain.identify.procedure import (
    GivenGains,
    Options,
    Problem,
    ProcedureResult,
    run_procedure,
)
from drivegain.identify.report import FORM_MARGIN, markdown_report, report_json
from drivegain.identify.runs import (
    CURRENT_CHANNELS,
    attached_payload,
    check_roles,
    load_gains,
    read_header,
)
from drivegain.identify.signal import check_reversal_mask

# --------------------------------------------------------------------------------------------
# Inputs


@dataclass(frozen=True)
class IdentifyRequest:
    """What to identify (the options of ``drivegain identify``, contracts §1).

    ``gains``: None identifies them when a loaded run is given (else uses the robot's a priori
    gains); ``"apriori"``, ``"gear-ratios"`` or a file (TOML ``values``/``std``, or a
    ``report.json``) fixes them and skips IDIM-WTLS.
    """

    robot: Path
    unloaded: Path
    out: Path
    loaded: Path | None = None
    payload: Path | None = None
    gains: str | None = None
    validate: Path | None = None
    validate_payload: Path | None = None
    friction: str | None = None
    estimator: str = "ml"  # --estimator: ml or paper (Estimator values)
    alpha: float | None = None
    cutoff: float | None = None
    sign_cutoff: float | None = None  # --sign-cutoff: velocity of the Coulomb columns' signs
    reversal_mask: float | None = None  # --reversal-mask: taper of the reversal mask, s
    reversal_mask_auto: bool = False  # --reversal-mask auto: on the drives that stick
    decimate: int | None = None
    reference: Path | None = None
    progress: bool = True
    plots: bool = True  # False: --no-plots, no figure is rendered (matplotlib not imported)
    consistent: cr.ConsistentRequest | None = None  # identify --consistent
    current: str = "reference"  # --current: reference or measured
    current_delay: float = 0.0  # --current-delay: age of the current samples, samples
    bootstrap: int = 0  # --bootstrap: replicates of the ML fit's block bootstrap (0: none)
    # Set by the pipeline, not an option: prepare with the Coulomb sign at the position cut-off
    # (the second candidate of identify.signchoice).
    sign_at_cutoff: bool = False
    # Set by the pipeline for --reversal-mask auto: the drives whose groups get the mask.
    reversal_mask_drives: tuple[int, ...] | None = None


#: what the report says when ``--no-plots`` skipped the figures
NO_PLOTS = "figures not rendered (--no-plots)"


# --------------------------------------------------------------------------------------------
# Progress display


class _Display:
    """A rich progress display on stderr, shown only on a terminal."""

    def __init__(self, enabled: bool):
        from rich.progress import (
            BarColumn,
            Progress,
            SpinnerColumn,
            TaskProgressColumn,
            TextColumn,
            TimeElapsedColumn,
        )

        from drivegain.console import console as shared_console

        console = shared_console(stderr=True)  # the log handler's too: lines go above the bar
        self.progress = Progress(
            SpinnerColumn(),
            TextColumn("{task.description}"),
            BarColumn(),
            TaskProgressColumn(),
            TimeElapsedColumn(),
            console=console,
            transient=True,
            disable=not (enabled and console.is_terminal),
        )

    def __enter__(self) -> _Display:
        self.progress.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self.progress.__exit__(None, None, None)


# --------------------------------------------------------------------------------------------
# The command


@dataclass(frozen=True)
class IdentifyOutcome:
    """What :func:`run_identify` produced."""

    result: ProcedureResult
    report: dict[str, Any]
    out: Path
    files: list[str]
    robot: Robot


def _check_request(req: IdentifyRequest) -> None:
    if req.current not in CURRENT_CHANNELS:
        raise InputError(f"expected one of {', '.join(CURRENT_CHANNELS)}", key="--current")
    if req.payload is not None and req.loaded is None:
        raise InputError("a payload file needs the loaded run it was fixed to", key="--loaded")
    if req.validate is not None and req.validate_payload is None:
        raise InputError("the validation run needs its payload file", key="--validate-payload")
    if req.validate_payload is not None and req.validate is None:
        raise InputError("a validation payload needs its run", key="--validate")
    if req.alpha is not None and not (math.isfinite(req.alpha) and req.alpha > 0):
        raise InputError(f"must be a positive number, got {req.alpha}", key="--alpha")
    if req.estimator not in {e.value for e in Estimator}:
        raise InputError(
            f"must be one of {', '.join(e.value for e in Estimator)}, got {req.estimator!r}",
            key="--estimator",
        )
    if req.alpha is not None and req.estimator != Estimator.PAPER:
        raise InputError(
            "α is a weight of the paper's estimator: add --estimator paper", key="--alpha"
        )
    if req.bootstrap:
        if req.bootstrap < MIN_REPLICATES:
            raise InputError(
                f"must be at least {MIN_REPLICATES} replicates, got {req.bootstrap}",
                key="--bootstrap",
            )
        if req.estimator != Estimator.ML or req.loaded is None or req.gains is not None:
            raise InputError(
                "the bootstrap is of the maximum-likelihood gains: it needs --loaded, the ml "
                "estimator and no --gains",
                key="--bootstrap",
            )
    for key, hz in (("--cutoff", req.cutoff), ("--sign-cutoff", req.sign_cutoff)):
        if hz is not None and not (math.isfinite(hz) and hz > 0):
            raise InputError(f"must be a positive number of Hz, got {hz}", key=key)
    if not (math.isfinite(req.current_delay) and 0.0 <= req.current_delay <= 1.0):
        raise InputError(
            f"must be between 0 and 1 sample, got {req.current_delay}", key="--current-delay"
        )
    check_reversal_mask(req.reversal_mask, key="--reversal-mask")
    if req.reversal_mask_auto and (req.loaded is None or req.gains is not None):
        raise InputError(
            "auto chooses the drives from the gains' fit: it needs --loaded and no --gains",
            key="--reversal-mask",
        )
    if req.decimate is not None and req.decimate < 1:
        raise InputError(f"must be an integer >= 1, got {req.decimate}", key="--decimate")
    if req.out.exists() and not req.out.is_dir():
        raise InputError("exists and is not a folder", file=req.out, key="--out")


@contextmanager
def _staging(out: Path) -> Iterator[Path]:
    """A temporary folder beside ``out``, moved into ``out`` on success, removed on failure
    (SIGTERM included: the command line turns it into an exception).

    Into an existing folder (maybe with the user's own files) our files are moved one by one,
    each replacement atomic, and the files an earlier identification listed in its report but
    this one did not write (plots of a form or a run no longer there) are removed, so the
    folder never mixes two runs' results.
    """
    parent = out.resolve().parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the output folder's parent: {exc}", file=out) from None
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=parent))
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if not out.exists():
        os.replace(tmp, out)
        return
    stale = set(_listed_files(out / "report.json")) - {p.name for p in tmp.iterdir()}
    for item in sorted(tmp.iterdir()):
        os.replace(item, out / item.name)
    for name in sorted(stale):
        (out / name).unlink(missing_ok=True)
    shutil.rmtree(tmp, ignore_errors=True)


def _listed_files(report: Path) -> list[str]:
    """The plain file names an earlier ``report.json`` says its identification wrote."""
    try:
        files = json.loads(report.read_text(encoding="utf-8")).get("files", [])
    except (OSError, ValueError, AttributeError, RecursionError):
        return []
    if not isinstance(files, list):
        return []
    return [f for f in files if isinstance(f, str) and f == Path(f).name and f]


def _reference_section(
    path: Path, result: ProcedureResult, bases: dict[WristFriction, Any]
) -> tuple[list[dict[str, Any]], str]:
    from drivegain.identify.reference import match_reference, read_reference, relative_difference

    refs = read_reference(path)
    bp = bases[result.friction]
    idx = match_reference(bp, refs)
    final = result.final
    rows: list[dict[str, Any]] = []
    md = [
        "",
        f"## Published values (`{path.name}`)",
        "",
        "Matched by regrouping expression; a comparison, not a truth.",
        "",
        "| parameter | ours | 2σ | published | %σ published | ours vs published % |",
        "|---|---|---|---|---|---|",
    ]
    for ref, i in zip(refs, idx, strict=True):
        if i is None:
            continue
        theirs = ref.values[-1]
        ours, std = float(final.base[i]), float(final.base_std[i])
        diff = relative_difference(ours, theirs)
        rsd = ref.rel_std_percent[-1]
        rows.append(
            {
                "name": final.base_names[i],
                "ours": ours,
                "std": std,
                "published": theirs,
                "published_rel_std_percent": rsd,
                "difference_percent": 100 * diff if math.isfinite(diff) else None,
            }
        )
        md.append(
            f"| {final.base_names[i]} | {ours:.4g} | {2 * std:.3g} | {theirs:.4g} | "
            f"{'–' if rsd is None else f'{rsd:.3g}'} | {100 * diff:+.1f} |"
        )
    md.append(f"\n{len(rows)} of {len(refs)} published parameters matched ours.")
    return rows, "\n".join(md) + "\n"


def run_identify(req: IdentifyRequest) -> IdentifyOutcome:
    """Identify from the request's logs and write the reports into ``req.out``.

    OpenBLAS runs single-threaded meanwhile (see :mod:`.blas`: its threads make the many small
    factorisations 10-25 times slower on busy cores).

    Raises
    ------
    InputError
        Bad options or files (nothing is written).
    IdentificationError
        The data cannot determine the unknowns (nothing is written).
    """
    with limited_blas_threads(1):
        if not req.plots:
            return _run_identify(req)
        from drivegain.identify import plots

        # matplotlib's import and the drawing go to a forked worker started now, so its
        # import overlaps the reading and the fit.
        plots.start_worker()
        try:
            return _run_identify(req)
        finally:
            plots.stop_worker()


def _run_identify(req: IdentifyRequest) -> IdentifyOutcome:
    _check_request(req)
    robot = load_robot(req.robot, acquisition=False)  # encoder counts etc. not needed here
    form = WristFriction(req.friction) if req.friction else robot.wrist_friction
    payload = load_payload(req.payload, robot.n) if req.payload is not None else None
    header_b = read_header(req.loaded) if req.loaded is not None else None
    check_roles(read_header(req.unloaded), header_b)
    if header_b is not None and payload is None:
        payload = attached_payload(header_b, robot.n)
    vpayload = (
        load_payload(req.validate_payload, robot.n) if req.validate_payload is not None else None
    )
    given = load_gains(req.gains, robot) if req.gains is not None else None
    if req.reference is not None and not req.reference.is_file():
        raise InputError("file not found", file=req.reference, key="--reference")
    model = build_model(robot)
    with _Display(req.progress) as display:
        specs: list[tuple[Path, str, Payload | None]] = [(req.unloaded, "unloaded", None)]
        if req.loaded is not None:
            specs.append((req.loaded, "loaded", payload))
        if req.validate is not None:
            specs.append((req.validate, "validation", vpayload))
        bases, loaded = load_and_prepare(model, specs, req, display.progress)
        made = None
        if req.loaded is not None and given is None:
            loaded, made, at_cutoff = prepchoice.sign_choice(
                model, specs, req, display.progress, robot, form, bases.get(form), loaded
            )
            if req.reversal_mask_auto:
                loaded, made = prepchoice.mask_choice(
                    model,
                    specs,
                    replace(req, sign_at_cutoff=at_cutoff),
                    display.progress,
                    form,
                    bases.get(form),
                    loaded,
                    made,
                )
        prepared = [x.prepared for x in loaded]
        infos = [x.info for x in loaded]
        metas = [x.meta for x in loaded]
        if given is None and req.loaded is None and metas[0].get("gains_hint") == "gear_ratio":
            given = GivenGains(robot.gear_ratios, None, "gear ratios (log's gains_hint)")
        by_label = {p.label: p for p in prepared}
        problem = Problem(
            robot=robot,
            bases=bases,
            unloaded=by_label["unloaded"],
            loaded=by_label.get("loaded"),
            validation=by_label.get("validation"),
            gains_fit=made,
        )
        task = display.progress.add_task("identification", total=None)
        options = Options(
            friction=form,
            gains=given,
            estimator=Estimator(req.estimator),
            alpha=req.alpha,
            bootstrap=req.bootstrap,
        )
        try:
            result = run_procedure(
                problem, options, step=lambda s: display.progress.update(task, description=s)
            )
        except IdentificationError as exc:
            if req.loaded is None or given is not None:
                raise
            raise IdentificationError(f"{exc}; {other_channel_hint(req.current)}") from None
        result.warnings.extend(current_warnings(result, req.current))
        display.progress.update(task, description="reports and plots")
        expressions = {
            name: expr
            for name, expr in zip(bases[form].names, bases[form].expressions, strict=True)
        }
        doc = report_json(result, robot, infos, expressions)
        doc["method"]["apriori_from_gear_ratio"] = list(robot.apriori_from_gear_ratio)
        with _staging(req.out) as tmp:
            if req.plots:
                from drivegain.identify import plots as plotting

                plots = plotting.write_plots(result, robot.joint_names, tmp)
            else:
                plots = {}
                doc["figures"] = NO_PLOTS
            md = markdown_report(doc, result, robot, infos, plots)
            if not req.plots:
                md += f"\n_{NO_PLOTS}._\n"
            if req.consistent is not None:
                out_c = cr.run_consistent(req.consistent, problem, result)
                doc["consistent"] = cr.consistent_json(out_c, problem, result)
                md += cr.consistent_markdown(doc["consistent"], robot)
            if req.reference is not None:
                rows, section = _reference_section(req.reference, result, bases)
                doc["reference"] = {"file": str(req.reference), "parameters": rows}
                md += section
            (tmp / "report.md").write_text(md, encoding="utf-8")
            # the same report as one self-contained file (figures embedded)
            from drivegain.identify.html import html_report

            (tmp / "report.html").write_text(
                html_report(md, tmp, f"Drive gain identification: {robot.name}"), encoding="utf-8"
            )
            # The files this identification wrote: a re-run into the folder removes what is
            # no longer produced (contracts §5, an added field).
            doc["files"] = sorted([*(p.name for p in tmp.iterdir()), "report.json"])
            (tmp / "report.json").write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
            files = sorted(p.name for p in tmp.iterdir())
        display.progress.remove_task(task)
    return IdentifyOutcome(result=result, report=doc, out=req.out, files=files, robot=robot)


def _summary(outcome: IdentifyOutcome, robot_names: list[str]) -> str:
    res = outcome.result
    doc = outcome.report
    m = doc["method"]
    lines = [
        f"identify: {m['estimator']}"
        + (f" (α = {m['alpha']:.3g})" if m["alpha"] is not None else "")
        + (f", friction form {m['friction']}" if outcome.robot.couplings else "")
        + f", {m['samples']} samples, gains: {res.gains_source}"
    ]
    # Columns as wide as the longest joint name; gains in N·m/A.
    w = max(6, *(len(nm) + 1 for nm in robot_names))
    lines.append(f"{'joint':<{w}}{'a priori':>10}{'gain':>10}{'2σ':>9}{'%σ':>7}  (N·m/A)")
    for j, name in enumerate(robot_names):
        std = "" if res.gains_std is None else f"{2 * res.gains_std[j]:9.3g}"
        rsd = "" if res.gains_std is None else f"{100 * res.gains_std[j] / abs(res.gains[j]):7.2f}"
        lines.append(f"{name:<{w}}{res.apriori[j]:10.4g}{res.gains[j]:10.4g}{std}{rsd}")
    fin = res.final
    if fin.payloads:
        p = fin.payloads[0]
        lines.append(
            f"payload {p.name}: mass {p.values[9]:.4g} ± {2 * p.std[9]:.2g} kg (2σ, "
            f"nominal {p.nominal[9]:.4g})"
        )
    lines.append(
        f"relative error norm {fin.relative_error:.4g} ({fin.name}), held-out "
        f"{res.cv.relative_error:.4g}; R² per joint " + " ".join(f"{v:.3f}" for v in fin.r2)
    )
    better, margin = res.better_form(), res.form_margin()
    if better is not None and margin is not None:
        lines.append(
            f"coupled-wrist friction form fitting held-out data better: {better.value} "
            f"(by {100 * margin:.2g} %{'' if margin >= FORM_MARGIN else ', not meaningful'})"
        )
    figures = "" if "figures" in doc else " and plots"
    lines.append(f"wrote {outcome.out}/report.json, report.md, report.html{figures}")
    if "figures" in doc:
        lines.append(doc["figures"])
    return "\n".join(lines)


def _mask_taper(value: float | str | None) -> float | None:
    """``--reversal-mask``'s taper: None for ``auto`` (the gate's taper comes later)."""
    return None if value is None or value == MASK_AUTO else float(value)


def identify_command(args: argparse.Namespace) -> int:
    """Handler of ``drivegain identify`` (options in :mod:`drivegain.cli`)."""
    req = IdentifyRequest(
        robot=args.robot,
        unloaded=args.unloaded,
        out=args.out,
        loaded=args.loaded,
        payload=args.payload,
        gains=args.gains,
        validate=args.validate,
        validate_payload=args.validate_payload,
        friction=args.friction,
        estimator=getattr(args, "estimator", None) or "ml",
        alpha=args.alpha,
        cutoff=args.cutoff,
        sign_cutoff=getattr(args, "sign_cutoff", None),
        reversal_mask=_mask_taper(getattr(args, "reversal_mask", None)),
        reversal_mask_auto=getattr(args, "reversal_mask", None) == MASK_AUTO,
        decimate=args.decimate,
        reference=getattr(args, "reference", None),
        progress=True,
        plots=not getattr(args, "no_plots", False),
        consistent=cr.request_from_args(args),
        current=getattr(args, "current", None) or "reference",
        current_delay=getattr(args, "current_delay", None) or 0.0,
        bootstrap=getattr(args, "bootstrap", None) or 0,
    )
    outcome = run_identify(req)
    print(_summary(outcome, outcome.robot.joint_names))
    if "consistent" in outcome.report:
        print(cr.summary_line(outcome.report["consistent"]))
    for w in outcome.result.warnings:
        print(f"drivegain: warning: {w}", file=sys.stderr)
    return 0
