"""Closed loops from many starts with one theta, advanced in lock-step: a batch.

:func:`rollouts` runs the closed loops that :func:`~mpcmobo.mpc.rollout` runs one after the
other (no sensitivities, optionally an exploration replayed) from ``n`` starts at once, on a
noise-free plant made of the system's equations with fixed parameters (the MPC's model for the
twin, ``true_params`` for J_eval). Every step of every loop is the solve of
:meth:`ParametricMPC.solve <mpcmobo.mpc.ParametricMPC.solve>`, with each loop's own warm start:

- the loops with a warm start take their Newton steps on the barrier KKT system together: one
  call of the Newton step ``map``-ped over the loops still iterating per step (CasADi
  ``Function.map``, evaluated column by column), with the acceptance tests of the solver's
  Newton path on all of them at once;
- a loop whose Newton steps do not converge, or without a warm start (the first step), is
  solved alone by ``ParametricMPC.solve`` from its own warm start (IPOPT, as in the sequential
  loop);
- the plant step of all loops is one call of the system's discrete step mapped over them.

A mapped function evaluates the same code on each column, so the records are those of the
sequential closed loops bit for bit (solve times aside; ``tests/test_batch.py`` checks it). A
loop whose plant diverges or runs away ends with the :class:`~mpcmobo.mpc.PlantDiverged` the
sequential loop raises; the others run on. ``docs/benchmarks.md`` (batch time) measures it.
"""

from __future__ import annotations

import time
import weakref
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from mpcmobo.mpc.closed_loop import RUNAWAY, PlantDiverged, _blank_record, not_finite
from mpcmobo.mpc.kkt import NumpyCall
from mpcmobo.mpc.parametric import ParametricMPC
from mpcmobo.mpc.records import EpisodeRecord
from mpcmobo.mpc.solve import MPCSolution
from mpcmobo.systems.base import System

__all__ = ["rollouts"]

# mapped functions (per function, batch size and shared inputs), kept while the function lives
_MAPS: weakref.WeakKeyDictionary[ca.Function, dict[tuple, NumpyCall]] = weakref.WeakKeyDictionary()


def mapped(fn: ca.Function, m: int, shared: tuple[bool, ...] | None = None) -> NumpyCall:
    """``fn`` evaluated on ``m`` columns at once (``Function.map``, serial), on numpy buffers;
    ``shared``: the inputs that are the same for all columns (given once). Cached."""
    maps = _MAPS.setdefault(fn, {})
    key = (m, shared)
    if key not in maps:
        if shared is None:
            maps[key] = NumpyCall(fn.map(m))
        else:
            maps[key] = NumpyCall(fn.map(m, list(shared), [False] * fn.n_out()))
    return maps[key]


def _columns(out: Any, m: int) -> np.ndarray:
    """A mapped output as (m, size): one row per column (a float when m = 1 and size 1)."""
    return np.asarray(out, float).reshape(-1, m).T if np.ndim(out) else np.full((m, 1), out)


@dataclass
class _Solved:
    """The solves of one step of ``m`` loops: what a record keeps of each, or its error."""

    action: np.ndarray  # (m, nu)
    value: np.ndarray  # (m,)
    slack: np.ndarray  # (m,)
    success: np.ndarray  # (m,)
    seconds: np.ndarray  # (m,)
    status: list[str]
    error: list[Exception | None]

    @classmethod
    def blank(cls, m: int, nu: int) -> _Solved:
        """Nothing solved yet."""
        nan = np.full(m, np.nan)
        z = np.zeros(m)
        return cls(np.zeros((m, nu)), nan, nan.copy(), z.astype(bool), z, [""] * m, [None] * m)

    def take(self, j: int, sol: MPCSolution | Exception) -> None:
        """Row ``j`` from a loop's own solve (or the exception it raised)."""
        if isinstance(sol, Exception):
            self.error[j] = sol
            return
        self.action[j], self.value[j], self.slack[j] = sol.action, sol.value, sol.slack
        self.success[j], self.seconds[j], self.status[j] = sol.success, sol.solve_time, sol.status


class _Batch:
    """The per-loop warm starts of the MPC's solver (``prev``, as the solver keeps its own)
    and the batched solve of one step."""

    def __init__(self, mpc: ParametricMPC, theta: np.ndarray, n: int) -> None:
        self.mpc, self.theta = mpc, theta
        self.problem, self.kkt, self.solver = mpc.problem, mpc.kkt, mpc.solver
        self.prev: list[dict | None] = [None] * n

    def solve(self, loops: np.ndarray, X: np.ndarray) -> _Solved:
        """The solve at the states ``X`` (m, nx) of ``loops`` (m,): Newton steps together,
        the others alone, each from its loop's warm start (module docstring)."""
        t0 = time.perf_counter()
        sv, m = self.solver, len(loops)
        P = np.hstack([X, np.broadcast_to(self.theta, (m, len(self.theta)))])
        out = _Solved.blank(m, self.problem.nu)
        warm = np.array([j for j in range(m) if self.prev[loops[j]] is not None], int)
        hit = np.zeros(m, bool)
        if sv.warm_start and sv.newton_steps and warm.size:
            Y, F, K, done = self.newton([self.prev[i] for i in loops[warm]], P[warm])
            rows = warm[done]
            self.accept(loops[rows], X[rows], Y[done], F[done], out, rows)
            hit[rows] = True
            out.seconds[rows] = (time.perf_counter() - t0) / m
        tried = np.zeros(m, bool)
        if sv.warm_start and sv.newton_steps:
            tried[warm] = True
        for j in map(int, np.flatnonzero(~hit)):  # the loop's own solve, its own warm start
            sv.prev = self.prev[loops[j]]
            try:
                out.take(j, self.own_solve(X[j], bool(tried[j])))
            except Exception as err:  # noqa: BLE001 - that loop fails, the others run on
                out.take(j, err)
            self.prev[loops[j]] = sv.prev
        return out

    def own_solve(self, x: np.ndarray, tried: bool) -> MPCSolution:
        """``ParametricMPC.solve`` at ``x`` from the solver's warm start; ``tried``: the Newton
        steps from it failed in the batch, so the solve's own Newton path (the same numbers,
        the same failure) returns None at once instead of taking them again."""
        return self.mpc.solve(x, self.theta, sensitivities=False, newton=not tried)

    def accept(
        self,
        loops: np.ndarray,
        X: np.ndarray,
        Y: np.ndarray,
        F: np.ndarray,
        out: _Solved,
        rows: np.ndarray,
    ) -> None:
        """``Solver.solution`` of the Newton roots ``Y`` (one per row, ``F`` their costs) at
        ``X``: rows ``rows`` of ``out``, and each loop's next warm start."""
        pr, sysm, s = self.problem, self.problem.system, len(loops)
        res, W, _ = self.kkt.solver_outputs(Y, F)
        plan_u = sysm.u_ref + pr.Su * W[:, pr.iu_flat].reshape(s, pr.N, pr.nu)
        out.action[rows] = np.clip(plan_u[:, 0], sysm.u_lb, sysm.u_ub)
        out.value[rows] = F * pr.cost_scale
        scale = np.tile(pr.slack_scale, pr.N + 1)
        out.slack[rows] = [float(np.sum(scale * w[pr.ie_flat])) for w in W]
        out.success[rows] = True
        for j in rows:
            out.status[j] = "Newton_Succeeded"
        shifted = pr.shifted(W, res["lam_g"], res["lam_x"])
        for r, i in enumerate(loops):
            self.prev[i] = {
                "w_shift": shifted[0][r],
                "lam_g": shifted[1][r],
                "lam_x": shifted[2][r],
                "plan_u": plan_u[r],
                "age": 0,
            }

    def newton(
        self, prevs: list[dict | None], P: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The solver's Newton path (``Solver.newton``) from each warm start in ``prevs`` with
        its parameters in ``P``: the points Y (m, ny), their costs, steps and whether they
        converged (m,)."""
        kkt, sv, m = self.kkt, self.solver, len(prevs)
        W = np.stack([prev["w_shift"] for prev in prevs])  # type: ignore[index]  # warm only
        lam_g = np.stack([prev["lam_g"] for prev in prevs])  # type: ignore[index]
        lam, mu = kkt.multipliers(W, lam_g, np.stack([prev["lam_x"] for prev in prevs]))  # type: ignore[index]
        Y = np.concatenate([W, lam, mu], axis=1)
        F, K, done = np.full(m, np.nan), np.zeros(m, int), np.zeros(m, bool)
        rows = np.flatnonzero(np.all(mu > 0, axis=1))  # the loops still taking steps
        for k in range(1, sv.newton_steps + 1):
            if rows.size == 0:
                break
            call = mapped(kkt.newton, rows.size)
            y_next, *scalars = call(Y[rows].ravel(), P[rows].ravel())
            res0, res, f, h_max, mu_min, h0_max = (_columns(v, rows.size)[:, 0] for v in scalars)
            good = (h0_max < 0) & (h_max < 0) & (mu_min > 0) & np.isfinite(res)
            Y[rows[good]] = _columns(y_next, rows.size)[good]
            conv = good & (res <= sv.tol)
            done[rows[conv]], F[rows[conv]], K[rows[conv]] = True, f[conv], k
            stop = (k == sv.newton_steps) | ((k >= 2) & (res > 0.1 * res0))
            rows = rows[good & ~conv & ~stop]
        return Y, F, K, done


def rollouts(
    system: System,
    mpc: ParametricMPC,
    theta: ArrayLike | None,
    x0s: ArrayLike,
    steps: int | None = None,
    *,
    plant_params: ArrayLike | None = None,
    noise: ArrayLike | None = None,
) -> list[EpisodeRecord | Exception]:
    """The closed loops of ``theta`` from each start in ``x0s`` (n, nx), ``steps`` steps each
    (None: the system's), run together (module docstring) on the plant made of the system's
    equations with ``plant_params`` (default ``true_params``), noise-free, with the
    exploration ``noise`` (steps, nu) replayed on each loop if given. Per start: the record of
    :func:`~mpcmobo.mpc.rollout` with ``sensitivities=False`` on that plant, or the exception
    that closed loop raised (a :class:`~mpcmobo.mpc.PlantDiverged`, a bad start)."""
    steps = int(system.episode_steps if steps is None else steps)
    if steps < 1:
        raise ValueError(f"an episode needs at least one step, got {steps}")
    theta = mpc.check_theta(theta)
    e = _checked_noise(noise, steps, system.nu)
    if plant_params is None and system.true_params is None:
        raise ValueError(
            f"{system.name} has no true plant (true_params is None): give plant_params"
        )
    p = np.asarray(system.true_params if plant_params is None else plant_params, float)
    starts = np.atleast_2d(np.asarray(x0s, float))
    n = starts.shape[0]
    out: list[EpisodeRecord | Exception] = []
    X = np.zeros((n, system.nx))
    for i, x0 in enumerate(starts):
        try:
            X[i] = system.check_state(x0)
            out.append(_blank_record(steps, system.nx, system.nu, theta, mpc.gamma))
        except ValueError as err:
            out.append(err)
    batch = _Batch(mpc, theta, n)
    try:
        for k in range(steps + 1):
            loops = np.array([i for i in range(n) if isinstance(out[i], EpisodeRecord)], int)
            if loops.size == 0:
                break
            _record(system, batch.solve(loops, X[loops]), out, loops, X, k, steps, e)
            loops = np.array([i for i in loops if isinstance(out[i], EpisodeRecord)], int)
            if k < steps and loops.size:
                _plant_step(system, out, loops, X, k, p)
    finally:
        mpc.reset()
    return out


def _checked_noise(noise: ArrayLike | None, steps: int, nu: int) -> np.ndarray | None:
    """The exploration to replay as a (steps, nu) array (None: none); a wrong shape or a value
    that is not finite is a ``ValueError``."""
    if noise is None:
        return None
    e = np.asarray(noise, float)
    if e.shape != (steps, nu):
        raise ValueError(f"noise must be ({steps}, {nu}), got {e.shape}")
    if not np.all(np.isfinite(e)):
        raise ValueError("the exploration noise contains NaN or inf")
    return e


def _record(
    system: System,
    sol: _Solved,
    out: list,
    loops: np.ndarray,
    X: np.ndarray,
    k: int,
    steps: int,
    noise: np.ndarray | None,
) -> None:
    """Record step ``k``'s state and solve of each of ``loops`` (as ``rollout`` records a
    solve), and the input it applies; a loop whose solve raised gets the exception."""
    for j, i in enumerate(loops):
        rec = out[i]
        if sol.error[j] is not None:
            out[i] = sol.error[j]
            continue
        rec.x[k] = X[i]
        rec.success[k], rec.solve_time[k] = sol.success[j], sol.seconds[j]
        rec.status.append(sol.status[j])
        if sol.success[j]:
            rec.V[k] = sol.value[j]
        if k < steps:
            rec.pi[k] = sol.action[j]
            if sol.success[j]:
                rec.slack[k] = sol.slack[j]
            u = sol.action[j] if noise is None else sol.action[j] + noise[k]
            rec.u[k] = system.clip_input(u)


def _plant_step(
    system: System, out: list, loops: np.ndarray, X: np.ndarray, k: int, p: np.ndarray
) -> None:
    """The plant step of ``loops`` from their states in ``X`` (x_{k+1} in place) with their
    stage costs and violations; a loop whose plant diverges gets its ``PlantDiverged``."""
    for i in loops:
        rec = out[i]
        rec.L[k] = system.stage_cost(X[i], rec.u[k])
        rec.violation[k] = system.constraint_violation(X[i], rec.u[k])
    U = np.array([out[i].u[k] for i in loops])
    step = mapped(system.discrete_step, loops.size, (False, False, True))
    X[loops] = _columns(step(X[loops].ravel(), U.ravel(), p)[0], loops.size)
    far = np.abs(X[loops] - system.x_ref) > RUNAWAY * np.asarray(system.x_scale, float)
    for j, i in enumerate(loops):
        x = X[i]
        if not np.all(np.isfinite(x)):
            stopped = not_finite(k, x)
        elif np.any(far[j]):
            names = ", ".join(nm for nm, f in zip(system.state_names, far[j]) if f)
            stopped = (
                f"the plant ran away at step {k}: state {x} ({names} more than {RUNAWAY:g} "
                "x_scale from x_ref); the episode is stopped"
            )
        else:
            continue
        out[i] = PlantDiverged(stopped, k, float(np.sum(out[i].violation[: k + 1])))
