"""The study's reference: J*, J_eval(theta0) and their evaluation episodes, computed once.

Every J_eval of a study is measured against the :class:`~mpcmobo.experiment.records.Reference`
that :func:`compute_reference` measures on the plant from the evaluation starts, before any
job runs; :func:`system_info` is what the figures need to know about the system.
"""

from __future__ import annotations

import hashlib
import time

import casadi as ca
import numpy as np

from mpcmobo.experiment import interrupts
from mpcmobo.experiment.build import build_system
from mpcmobo.experiment.evaluation import make_evaluator, mean_cost, no_J_star_reason
from mpcmobo.experiment.loop import EPISODE_FAILURES
from mpcmobo.experiment.records import Reference, Trajectory
from mpcmobo.experiment.rundir import ReferenceFailed, RunDirectory, StudyError
from mpcmobo.experiment.settings import Settings
from mpcmobo.experiment.training_reference import training_references
from mpcmobo.systems.base import System


def system_info(system: System) -> dict:
    """What the figures need to know about the system (JSON-safe: inf -> None)."""
    return {
        "name": system.name,
        "description": system.description,
        "state_names": list(system.state_names),
        "input_names": list(system.input_names),
        "dt": float(system.dt),
        "x_ref": system.x_ref.tolist(),
        "u_ref": system.u_ref.tolist(),
        "x_lb": system.x_lb.tolist(),
        "x_ub": system.x_ub.tolist(),
        "u_lb": system.u_lb.tolist(),
        "u_ub": system.u_ub.tolist(),
        "theta_names": list(system.parameterization.names),
        "param_names": list(system.param_names),
        "nominal_params": np.asarray(system.models["imperfect"], float).tolist(),
        "true_params": None
        if system.true_params is None
        else np.asarray(system.true_params, float).tolist(),
        **_cost_info(system),
        "equations": equations_fingerprint(system),
    }


def _cost_info(system: System) -> dict:
    """The RL stage cost's weights, the initial-state box and theta0: what J_eval and every
    learner's evidence are measured with, compared like the other fields on a resume."""
    Gamma_h = system.Gamma_h
    return {
        "Q": np.asarray(system.Q, float).tolist(),
        "R": np.asarray(system.R, float).tolist(),
        "Gamma": np.asarray(system.Gamma, float).tolist(),
        "Gamma_h": None if Gamma_h is None else np.asarray(Gamma_h, float).tolist(),
        "x0_lb": np.asarray(system.x0_lb, float).tolist(),
        "x0_ub": np.asarray(system.x0_ub, float).tolist(),
        "theta0": np.asarray(system.parameterization.theta0, float).tolist(),
    }


def equations_fingerprint(system: System) -> dict:
    """A hash of the system's equations (its discrete step and path constraints, as CasADi
    serialises them) and the CasADi version that serialised them: what tells a resumed run
    that the system's code changed under it."""
    digest = hashlib.sha1(system.discrete_step.serialize().encode())
    if system.path_function is not None:
        digest.update(system.path_function.serialize().encode())
    return {"casadi": ca.CasadiMeta.version(), "hash": digest.hexdigest()}


# what a change of does not change the system (its words)
_NOT_COMPARED = ("description", "equations")


def check_run_system(run_dir: RunDirectory) -> None:
    """Before a saved run or tuner goes on (and before anything of it is written): refuse
    where its system changed since its reference was computed (:func:`check_same_system`); a
    run of an older version is refused as such first."""
    if not run_dir.holds_run():
        return
    run_dir.check_schema()
    reference = run_dir.reference()
    if reference is not None:
        settings = run_dir.saved_settings()
        what = f"{'tuner' if run_dir.is_tuner() else 'run'} in {run_dir.path}"
        if settings.system.factory is not None:
            what += f" (its system from {settings.system.factory})"
        check_same_system(saved_system(reference), build_system(settings), what)


def saved_system(reference: Reference) -> dict:
    """The :func:`system_info` a reference was computed with, with its theta0 (a run saved
    before ``system_info`` held theta0 has it in the reference alone)."""
    return {"theta0": np.asarray(reference.theta0, float).tolist(), **reference.system}


def check_same_system(saved: dict, system: System, what: str) -> None:
    """Refuse (:class:`StudyError`) to go on with ``what`` (the run or tuner, in words) when
    ``system`` is not the one its reference was computed with (``saved``: its
    :func:`system_info`): a field that differs, or equations whose fingerprint differs under
    the same CasADi. A run saved before the fingerprint existed is compared on the other
    fields."""
    now = system_info(system)
    changed = [k for k in now if k in saved and k not in _NOT_COMPARED and saved[k] != now[k]]
    before, after = saved.get("equations"), now["equations"]
    if isinstance(before, dict) and before.get("casadi") == after["casadi"]:
        if before.get("hash") != after["hash"]:
            changed.append("its equations (dynamics or path constraints)")
    if changed:
        raise StudyError(
            f"the system is not the one the {what} was made with: {', '.join(changed)} "
            "changed since, and the records would mix two systems. Go on with the system as "
            "it was, or start anew in another directory"
        )


def compute_reference(settings: Settings) -> Reference:
    """J*, J_eval(theta0) and the evaluation episodes of theta0 ("initial") and perfect MPC."""
    system = build_system(settings)
    evaluator = make_evaluator(settings, system)
    phases: list[tuple[str, str, np.ndarray | None]] = [
        ("initial", "imperfect", evaluator.mpc("imperfect").theta0.copy())
    ]
    if evaluator.has_J_star:
        phases.append(("perfect", "perfect", None))
    for _, model, _ in phases:  # an interrupt ends a solve, never fails it
        interrupts.guard_solves(evaluator.mpc(model))
    theta0 = evaluator.mpc("imperfect").theta0.copy()
    t0 = time.perf_counter()
    trajectories = []
    values = {}
    for phase, model, theta in phases:
        try:
            eps = evaluator.episodes(theta, model)
        except EPISODE_FAILURES as err:
            what = "J(theta0), theta0's MPC" if phase == "initial" else "J*, the perfect MPC"
            raise ReferenceFailed(
                f"computing {what} on the plant from the evaluation starts failed: "
                f"{type(err).__name__}: {err}. Every J_eval is measured against these; check the "
                "plant (docs/user-systems.md) and run again"
            ) from None
        values[phase] = mean_cost(eps)
        trajectories += [
            Trajectory(phase, -1, i, r.x.copy(), r.u.copy()) for i, r in enumerate(eps)
        ]
    # J~*, like for like: needs the perfect model
    training = training_references(settings, system) if evaluator.has_J_star else []
    return Reference(
        J_star=values.get("perfect"),
        J_initial=values["initial"],
        theta0=theta0,
        system=system_info(system),
        trajectories=trajectories,
        wall_time_s=time.perf_counter() - t0,
        J_star_missing=None if evaluator.has_J_star else no_J_star_reason(system),
        training=training,
    )
