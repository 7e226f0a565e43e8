"""One MPC solve and its paths: Newton steps, IPOPT warm-started, IPOPT cold, the fallback input.

:meth:`Solver.solve` tries, in order:

1. with a warm start (the previous solution and its multipliers, shifted by one stage), at most
   ``newton_steps`` Newton steps on the KKT residual ``R(y, p) = 0`` of :mod:`mpcmobo.mpc.kkt`
   with a fraction-to-boundary rule. They reach the root of ``R`` in 3-4 steps when the active
   set does not change; accepted at ``|R|_inf <= tol`` at a strictly interior point, it is the
   point IPOPT stops at;
2. when they cannot start or do not converge (typically because the new state violates a
   state bound of the shifted plan), the interior-point continuation of
   :mod:`mpcmobo.mpc.interior` on the same Newton system, ending at the same root, accepted
   only at a minimum (:meth:`~mpcmobo.mpc.kkt.KKTSystem.is_minimum`: from a re-centred start
   the path can end at a saddle point, dearer, where IPOPT finds the minimum); where it
   fails or ends at a saddle, the same continuation restarted from the shifted plan on the
   central path (the previous multipliers dropped), accepted at a minimum too;
3. without a warm start, the same continuation from the cold guess, accepted at a minimum
   (these two paths with a ``Continuation``; none of the three with ``newton_steps = 0``);
4. IPOPT from the warm start (when the continuations do not get there either);
5. IPOPT from a cold start (when the warm start misled it, or there is none);
6. the fallback input when IPOPT fails: the shifted previous plan, else ``u_r``, with NaN value
   and gradients.

A solution gives the policy ``pi_theta(x)``, the first input of the plan clipped to the input
bounds (eq. Policy), the value and, if asked, the sensitivities; shifted, it is the next warm
start. Everything is returned as an :class:`MPCSolution`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np

from mpcmobo.mpc.interior import (
    RESTART_BARRIER,
    Continuation,
    cold_continuation,
    continuation,
    recentre,
)
from mpcmobo.mpc.kkt import KKTSystem
from mpcmobo.mpc.transcription import Transcription

SUCCESS = frozenset({"Solve_Succeeded", "Solved_To_Acceptable_Level"})
# options of CasADi's nlpsol itself (not IPOPT's): passed without the "ipopt." prefix
CASADI_NLPSOL_KEYS = (
    "print_time",
    "show_eval_warnings",
    "calc_lam_p",
    "calc_lam_x",
    "calc_f",
    "calc_g",
    "bound_consistency",
    "record_time",
)
# what a warm path returns: the arguments of Solver.solution (IPOPT-style outputs, w, status,
# steps and the multipliers (lambda, mu))
Found = tuple[dict, np.ndarray, str, int, tuple[np.ndarray, np.ndarray]]


@dataclass
class MPCSolution:
    """Result of one MPC solve at state ``x`` with parameters ``theta``."""

    action: np.ndarray  # (nu,) pi_theta(x), or the fallback input when the solve failed
    value: float  # V_theta(x) (NaN when failed)
    dpi_dtheta: np.ndarray | None  # (n_theta, nu)
    dV_dtheta: np.ndarray | None  # (n_theta,)
    success: bool
    status: str
    slack: float = 0.0  # sum of the slacks eta, physical units
    iterations: int = 0
    plan_u: np.ndarray | None = None  # (N, nu) predicted inputs
    plan_x: np.ndarray | None = None  # (N+1, nx) predicted states
    solve_time: float = 0.0  # seconds, solve + sensitivities
    fallback: bool = False
    info: dict = field(default_factory=dict)


def ipopt_options(
    tol: float,
    tau: float,
    max_iter: int,
    *,
    options: dict | None = None,
    warm: dict | None = None,
) -> tuple[dict, dict]:
    """CasADi ``nlpsol`` options of the cold and of the warm-started IPOPT solver.

    IPOPT stops at the barrier parameter ``tau`` (``mu_target``, the point that eq. nabla_pi
    differentiates). ``options`` go to both solvers, then ``warm`` to the warm one only, after its
    warm-start settings; a key is an IPOPT option (``"max_iter"`` or ``"ipopt.max_iter"``) unless
    it is one of CasADi's own (``"print_time"``, ``"show_eval_warnings"``).
    """
    cold = {
        "ipopt.print_level": 0,
        "print_time": False,
        # lam_p (the multipliers of the parameters) costs one more gradient evaluation per
        # solve and is not used: the sensitivities come from the KKT system
        "calc_lam_p": False,
        # IPOPT may probe wild iterates (Inf/NaN in the model): it backtracks by
        # itself, and a failed solve is reported in MPCSolution, so CasADi's per-evaluation
        # warnings on stderr are only noise that would bury the progress bars
        "show_eval_warnings": False,
        "ipopt.sb": "yes",
        "ipopt.tol": tol,
        "ipopt.acceptable_tol": max(1e-6, 100 * tol),
        "ipopt.mu_target": tau,
        "ipopt.max_iter": max_iter,
        "ipopt.bound_relax_factor": 0.0,
        "ipopt.honor_original_bounds": "no",
        "ipopt.nlp_scaling_method": "none",
    }
    cold.update(casadi_keys(options))
    warm_opts = {
        **cold,
        "ipopt.warm_start_init_point": "yes",
        "ipopt.warm_start_bound_push": 1e-6,
        "ipopt.warm_start_mult_bound_push": 1e-6,
        "ipopt.mu_init": 1e-3,
        "ipopt.max_iter": min(max_iter, 50),
    }
    warm_opts.update(casadi_keys(warm))
    return cold, warm_opts


def casadi_keys(options: dict | None) -> dict:
    """User solver options with IPOPT's keys prefixed ``ipopt.`` as CasADi expects."""
    own = CASADI_NLPSOL_KEYS
    return {
        k if k.startswith("ipopt.") or k in own else f"ipopt.{k}": v
        for k, v in (options or {}).items()
    }


class Solver:
    """The solve paths of one MPC: IPOPT (``cold``, and ``warm`` when ``warm_start``) on the
    NLP ``nlp`` (a :class:`~mpcmobo.mpc.transcription.Transcription`'s dictionary, or the path
    of a compiled library that holds it), the Newton steps on its :class:`KKTSystem`, and the
    warm start they share (``prev``: the shifted previous solution ``w_shift``, its multipliers
    ``lam_g``, ``lam_x``, the plan ``plan_u`` and ``age``, the solves since it was made).

    ``tol``: the acceptance test of the Newton steps (``|R|_inf``) and IPOPT's tolerance;
    ``newton_steps``: the most Newton steps of a warm solve (0: IPOPT only);
    ``interior``: the settings of the continuations after them and from the cold guess
    (None: IPOPT right away);
    ``max_iter``, ``solver_options``, ``warm_options``: see :func:`ipopt_options`.

    :meth:`solve` reaches its paths through the instance's methods :meth:`newton`,
    :meth:`interior_point`, :meth:`restarted_interior_point`, :meth:`cold_interior_point`,
    :meth:`ipopt` and :meth:`sensitivities`, so a test injects a failure or a benchmark a timer
    by replacing one of them on the instance (their signatures and returns are documented).
    """

    def __init__(
        self,
        problem: Transcription,
        kkt: KKTSystem,
        nlp: dict | str,
        *,
        tol: float,
        max_iter: int,
        newton_steps: int,
        warm_start: bool,
        solver_options: dict | None = None,
        warm_options: dict | None = None,
        interior: Continuation | None = None,
    ) -> None:
        self.problem, self.kkt, self.interior = problem, kkt, interior
        self.tol, self.newton_steps, self.warm_start = float(tol), newton_steps, bool(warm_start)
        cold, warm = ipopt_options(
            tol, kkt.tau, max_iter, options=solver_options, warm=warm_options
        )
        self.cold = ca.nlpsol("mpc", "ipopt", nlp, cold)
        self.cold_options = cold  # the cold solver's options (the exported controller's)
        self.warm: ca.Function | None = (
            ca.nlpsol("mpc_warm", "ipopt", nlp, warm) if self.warm_start else None
        )
        self.prev: dict | None = None

    def reset(self) -> None:
        """Forget the warm start."""
        self.prev = None

    def solve(
        self, x: np.ndarray, theta: np.ndarray, sensitivities: bool, newton: bool = True
    ) -> MPCSolution:
        """Solve at state ``x`` with parameters ``theta`` (both checked) by the first path
        that succeeds (see the module docstring); ``newton=False``: without the Newton steps
        (a caller that took them already and saw them fail)."""
        t0 = time.perf_counter()
        p = np.concatenate([x, theta])
        warm = self.warm_start and self.prev is not None
        found = None
        if warm and self.newton_steps:
            found = self.newton(p) if newton else None
            if found is None:  # both continuations give None without their settings
                found = self.interior_point(p)
            if found is None:
                found = self.restarted_interior_point(p)
        elif self.newton_steps and self.interior is not None:
            found = self.cold_interior_point(x, p)
        if found is not None:
            sol = self.solution(x, p, *found, sensitivities=sensitivities)
            sol.solve_time = time.perf_counter() - t0
            return sol
        ok, status, iters, out, wopt = self.ipopt(x, p, warm)
        if not ok and warm:  # a warm start can mislead IPOPT: retry once from a cold start
            ok, status, iters2, out, wopt = self.ipopt(x, p, False)
            iters += iters2
        if not ok:
            sol = self.failed(status, iters, sensitivities)
        else:
            sol = self.solution(x, p, out, wopt, status, iters, sensitivities=sensitivities)
        sol.solve_time = time.perf_counter() - t0
        return sol

    def newton(self, p: np.ndarray) -> Found | None:
        """Newton steps on R(y, p) = 0 from the shifted previous solution (``newton_steps``).

        Returns the arguments of :meth:`solution` (IPOPT-style outputs, w, status, steps, and
        the multipliers (lambda, mu)) when ``|R|_inf <= tol`` at a point with ``H < 0``,
        ``mu > 0``; None when the steps do not get there (IPOPT then solves)."""
        prev = self.prev
        if prev is None:
            return None
        w = prev["w_shift"]
        lam, mu = self.kkt.multipliers(w, prev["lam_g"], prev["lam_x"])
        y = np.concatenate([w, lam, mu])
        if not np.all(mu > 0):
            return None
        for k in range(1, self.newton_steps + 1):
            y_next, *scalars = self.kkt.newton_call(y, p)
            res0, res, f, h_max, mu_min, h0_max = (float(v) for v in scalars)
            # not interior (the new state violates a row of the old plan), not converging
            # (from the 2nd step on, the residual must fall tenfold per step), or out of steps
            if not (h0_max < 0 and h_max < 0 and mu_min > 0 and np.isfinite(res)):
                return None
            y = np.asarray(y_next).reshape(-1)
            if res <= self.tol:
                break
            if k == self.newton_steps or (k >= 2 and res > 0.1 * res0):
                return None
        out, w, mult = self.kkt.solver_outputs(y, f)
        return out, w, "Newton_Succeeded", k, mult

    def interior_point(self, p: np.ndarray) -> Found | None:
        """The interior-point continuation from the shifted previous solution
        (:mod:`mpcmobo.mpc.interior`): the arguments of :meth:`solution`, as :meth:`newton`
        returns them, or None when it does not reach ``|R|_inf <= tol`` (IPOPT then solves)."""
        prev, settings = self.prev, self.interior
        if prev is None or settings is None:
            return None
        w = prev["w_shift"]
        lam, mu = self.kkt.multipliers(w, prev["lam_g"], prev["lam_x"])
        y = recentre(self.kkt, w, lam, mu, p, settings)
        got = None if y is None else continuation(self.kkt, y, p, self.tol, settings)
        return self._at_minimum(got, p, "Continuation_Succeeded")

    def restarted_interior_point(self, p: np.ndarray) -> Found | None:
        """The continuation restarted from the shifted previous plan on the central path,
        without the previous multipliers (:func:`~mpcmobo.mpc.interior.cold_continuation` with
        ``RESTART_BARRIER``): the arguments of :meth:`solution`, or None (IPOPT then
        solves)."""
        prev, settings = self.prev, self.interior
        if prev is None or settings is None:
            return None
        got = cold_continuation(
            self.kkt, prev["w_shift"], p, self.tol, settings, barriers=(RESTART_BARRIER,)
        )
        return self._at_minimum(got, p, "Restart_Continuation_Succeeded")

    def cold_interior_point(self, x: np.ndarray, p: np.ndarray) -> Found | None:
        """The continuation from the cold guess at ``x`` (:func:`~mpcmobo.mpc.interior.
        cold_continuation`): the arguments of :meth:`solution`, or None (IPOPT then solves)."""
        if self.interior is None:
            return None
        w0 = self.problem.cold_guess(x)
        got = cold_continuation(self.kkt, w0, p, self.tol, self.interior)
        return self._at_minimum(got, p, "Cold_Continuation_Succeeded")

    def _at_minimum(
        self, got: tuple[np.ndarray, float, int] | None, p: np.ndarray, status: str
    ) -> Found | None:
        """A continuation's root ``got`` (its point, cost and steps) as the arguments of
        :meth:`solution` with ``status``, if it is a minimum
        (:meth:`~mpcmobo.mpc.kkt.KKTSystem.is_minimum`); else None (IPOPT then solves)."""
        if got is None or not self.kkt.is_minimum(got[0], p):
            return None
        y, f, steps = got
        out, w, mult = self.kkt.solver_outputs(y, f)
        return out, w, status, steps, mult

    def ipopt(self, x: np.ndarray, p: np.ndarray, warm: bool) -> tuple[bool, str, int, Any, Any]:
        """IPOPT from the warm start (``warm``) or the cold guess: (ok, status, iterations,
        IPOPT's outputs, w); outputs and w are None when IPOPT raised."""
        if warm:
            w0, lam_g0, lam_x0 = self.prev["w_shift"], self.prev["lam_g"], self.prev["lam_x"]  # type: ignore[index]  # warm: prev is set
        else:
            w0, lam_g0, lam_x0 = self.problem.cold_guess(x), None, None
        pr = self.problem
        args = {"x0": w0, "p": p, "lbx": pr.lbw, "ubx": pr.ubw, "lbg": pr.lbg, "ubg": pr.ubg}
        if lam_g0 is not None:
            args["lam_g0"], args["lam_x0"] = lam_g0, lam_x0
        solver: ca.Function = self.warm if warm else self.cold  # type: ignore[assignment]  # warm: built
        try:
            out = solver(**args)
        except RuntimeError as err:  # IPOPT can raise on evaluation errors
            return False, f"Exception: {err}", 0, None, None
        st = solver.stats()
        status, iters = st.get("return_status", "unknown"), int(st.get("iter_count", 0))
        wopt = np.asarray(out["x"]).reshape(-1)
        ok = status in SUCCESS and bool(np.all(np.isfinite(wopt)))
        return ok, status, iters, out, wopt

    def sensitivities(
        self,
        w: np.ndarray,
        lam_g: np.ndarray,
        lam_x: np.ndarray,
        p: np.ndarray,
        mult: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(dpi/dtheta, dV/dtheta) at a solution (eq. nabla_pi, grad V); ``mult``: its
        (lambda, mu) when known (Newton), else recovered from IPOPT's multipliers."""
        lam, mu = self.kkt.multipliers(w, lam_g, lam_x) if mult is None else mult
        return self.kkt.sensitivities(w, lam, mu, p)

    def solution(
        self,
        x: np.ndarray,
        p: np.ndarray,
        out: dict[str, ca.DM],
        wopt: np.ndarray,
        status: str,
        iters: int,
        mult: tuple[np.ndarray, np.ndarray] | None = None,
        sensitivities: bool = True,
    ) -> MPCSolution:
        """pi_theta(x) (eq. Policy), V_theta(x), the plan and, if asked, the sensitivities;
        the solution, shifted, is the next warm start."""
        lam_g = np.asarray(out["lam_g"]).reshape(-1)
        lam_x = np.asarray(out["lam_x"]).reshape(-1)
        plan_u, plan_x, slack = self.problem.plan(x, wopt)
        sol = MPCSolution(
            action=self.problem.system.clip_input(plan_u[0]),
            value=float(out["f"]) * self.problem.cost_scale,
            dpi_dtheta=None,
            dV_dtheta=None,
            success=True,
            status=status,
            slack=slack,
            iterations=iters,
            plan_u=plan_u,
            plan_x=plan_x,
        )
        if sensitivities:
            n_theta, nu = self.problem.n_theta, self.problem.nu
            try:
                sol.dpi_dtheta, sol.dV_dtheta = self.sensitivities(wopt, lam_g, lam_x, p, mult)
            except (RuntimeError, ValueError) as err:  # singular KKT matrix
                sol.dpi_dtheta = np.full((n_theta, nu), np.nan)
                sol.dV_dtheta = np.full(n_theta, np.nan)
                sol.info["sensitivity_error"] = str(err)
        self.remember(wopt, lam_g, lam_x, plan_u)
        return sol

    def failed(self, status: str, iters: int, sensitivities: bool) -> MPCSolution:
        """The fallback input (the previous plan, one step older) and NaN value and gradients."""
        act = self.fallback_action()
        if self.prev is not None:
            self.prev["age"] += 1
        n_theta, nu = self.problem.n_theta, self.problem.nu
        return MPCSolution(
            action=act,
            value=np.nan,
            dpi_dtheta=np.full((n_theta, nu), np.nan) if sensitivities else None,
            dV_dtheta=np.full(n_theta, np.nan) if sensitivities else None,
            success=False,
            status=status,
            slack=np.nan,
            iterations=iters,
            fallback=True,
        )

    def remember(
        self, w: np.ndarray, lam_g: np.ndarray, lam_x: np.ndarray, plan_u: np.ndarray | None
    ) -> None:
        """Store the solution and its multipliers, shifted by one stage, as the next warm start."""
        w_shift, lam_g_shift, lam_x_shift = self.problem.shifted(w, lam_g, lam_x)
        self.prev = {
            "w_shift": w_shift,
            "lam_g": lam_g_shift,
            "lam_x": lam_x_shift,
            "plan_u": plan_u,
            "age": 0,
        }

    def fallback_action(self) -> np.ndarray:
        """The safe input used when a solve fails: the shifted previous plan, else ``u_r``."""
        system = self.problem.system
        if self.prev is not None and self.prev["plan_u"] is not None:
            plan = self.prev["plan_u"]
            age = min(self.prev["age"] + 1, plan.shape[0] - 1)
            return system.clip_input(plan[age])
        return system.clip_input(system.u_ref)
