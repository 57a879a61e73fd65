"""Which preparation of the runs ``identify`` keeps, once they are read and prepared.

Two choices, each preparing the runs again when it changes something: the velocity whose sign
the Coulomb columns take (:mod:`.signchoice`: the likelier fit of runs a and b), then, with
``--reversal-mask auto``, the reversal mask on the drives that stick (:mod:`.maskgate`). Each
hands on the fit of runs a and b it made when the runs it returns are the ones it fitted, so
the procedure does not fit them again (:class:`~.procedure.FitMade`).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from drivegain.config.payload import Payload
from drivegain.config.robot import Robot, WristFriction
from drivegain.dynamics.base import BaseParameters
from drivegain.dynamics.model import RobotModel
from drivegain.errors import IdentificationError
from drivegain.identify.design import make_design
from drivegain.identify.loading import Loaded, load_and_prepare
from drivegain.identify.maskgate import AUTO_TAPER_S, gate_note, stuck_drives
from drivegain.identify.ml import ml_fit
from drivegain.identify.procedure import FitMade, long_runs
from drivegain.identify.signchoice import choose_sign, has_choice

if TYPE_CHECKING:  # the request is the command's; only its fields are read here
    from drivegain.identify.pipeline import IdentifyRequest


def sign_choice(
    model: RobotModel,
    specs: list[tuple[Path, str, Payload | None]],
    req: IdentifyRequest,
    progress: Any,
    robot: Robot,
    form: WristFriction,
    bp: BaseParameters | None,
    loaded: list[Loaded],
) -> tuple[list[Loaded], FitMade | None, bool]:
    """``loaded``, or the runs prepared again with the Coulomb sign at the position cut-off
    when that explains runs a and b's currents better (:mod:`.signchoice`); the report's runs
    say which, and by how much. With them the kept preparation's fit of runs a and b, for the
    gains' estimate (None when there was no choice), and whether the second preparation was
    kept. ``bp``: the friction form's base parameters (None: the procedure reports the form
    missing). Both preparations are held until the choice: peak memory about twice one's."""
    payload = loaded[1].prepared.payload
    if bp is None or payload is None:  # the procedure reports either
        return loaded, None, False
    if not has_choice(x.prepared.filter for x in loaded):
        return loaded, None, False
    # Every run again, not only a and b: the stored columns depend on all runs' payloads.
    _, other = load_and_prepare(model, specs, replace(req, sign_at_cutoff=True), progress)
    pairs = [
        (make_design(x[0].prepared, bp, form, robot), make_design(x[1].prepared, bp, form, robot))
        for x in (loaded, other)
    ]
    task = progress.add_task("Coulomb sign: which velocity", total=None)
    choice = choose_sign(pairs, payload, parallel=long_runs(list(pairs[0])))
    progress.remove_task(task)
    kept = loaded if choice.chosen == 0 else other
    runs = with_note(kept, choice.note())
    # the prepared runs themselves (not copies): the procedure checks that they are its own
    made = (
        None
        if choice.fit is None
        else FitMade(form, kept[0].prepared, kept[1].prepared, choice.fit)
    )
    return runs, made, choice.chosen != 0


def mask_choice(
    model: RobotModel,
    specs: list[tuple[Path, str, Payload | None]],
    req: IdentifyRequest,
    progress: Any,
    form: WristFriction,
    bp: BaseParameters | None,
    loaded: list[Loaded],
    made: FitMade | None,
) -> tuple[list[Loaded], FitMade | None]:
    """``--reversal-mask auto``: the runs prepared again with the reversal mask on the drives
    whose κ̂ says they stick (:mod:`.maskgate`), or ``loaded`` itself when none does; each run
    notes the choice. ``made``: the unmasked preparation's fit of runs a and b when the sign's
    choice made one (otherwise made here, and handed on when nothing is masked)."""
    payload = loaded[1].prepared.payload
    if bp is None or payload is None:  # the procedure reports either
        return loaded, made
    robot = model.robot
    if made is None:
        task = progress.add_task("reversal mask: which drives stick", total=None)
        a, b = (make_design(x.prepared, bp, form, robot) for x in loaded[:2])
        # with the errors-in-variables test's sums, as the sign's choice fits (the procedure
        # takes this fit when nothing is masked)
        try:
            fit = ml_fit(a, b, payload, parallel=long_runs([a, b]), influence=True)
        except IdentificationError as exc:  # the procedure's own fit reports it, if it needs one
            note = f"reversal mask (auto): not chosen, the unmasked fit failed ({exc})"
            return with_note(loaded, note), None
        finally:
            progress.remove_task(task)
        made = FitMade(form, loaded[0].prepared, loaded[1].prepared, fit)
    kappa = made.fit.kappa
    drives = stuck_drives(kappa)
    note = gate_note(robot, kappa, drives)
    if drives:
        again = replace(req, reversal_mask=AUTO_TAPER_S, reversal_mask_drives=drives)
        loaded = load_and_prepare(model, specs, again, progress)[1]
        made = None  # the procedure fits the masked runs
    # the prepared runs stay the same objects: a fit made of them still serves the procedure
    return with_note(loaded, note), made


def with_note(loaded: list[Loaded], note: str) -> list[Loaded]:
    """``loaded`` with ``note`` added to every run's notes (the same prepared runs)."""
    return [replace(x, info=replace(x.info, notes=[*x.info.notes, note])) for x in loaded]
