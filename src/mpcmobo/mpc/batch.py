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
from typing import Any

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from mpcmobo.mpc.closed_loop import RUNAWAY, PlantDiverged, _blank_record, _record_solve
from mpcmobo.mpc.kkt import NumpyCall
from mpcmobo.mpc.parametric import ParametricMPC
from mpcmobo.mpc.records import EpisodeRecord
from mpcmobo.mpc.solve import MPCSolution
from mpcmobo.systems.base import System

__all__ = ["rollouts"]

# mapped functions (one per function and batch size), kept while the function lives
_MAPS: weakref.WeakKeyDictionary[ca.Function, dict[int, NumpyCall]] = weakref.WeakKeyDictionary()


def mapped(fn: ca.Function, m: int, shared: tuple[bool, ...] | None = None) -> NumpyCall:
    """``fn`` evaluated on ``m`` columns at once (``Function.map``, serial), on numpy buffers;
    ``shared``: the inputs that are the same for all columns (given once). Cached."""
    maps = _MAPS.setdefault(fn, {})
    if m not in maps:
        if shared is None:
            maps[m] = NumpyCall(fn.map(m))
        else:
            maps[m] = NumpyCall(fn.map(m, list(shared), [False] * fn.n_out()))
    return maps[m]


def _columns(out: Any, m: int) -> np.ndarray:
    """A mapped output as (m, size): one row per column (a float when m = 1 and size 1)."""
    return np.asarray(out, float).reshape(-1, m).T if np.ndim(out) else np.full((m, 1), out)


def _parts(mpc: ParametricMPC) -> tuple[Any, Any, Any]:
    """The MPC's transcription, KKT system and solve paths."""
    names = (("problem", "_problem"), ("kkt", "_kkt_system"), ("solver", "_paths"))
    found = [getattr(mpc, public, None) or getattr(mpc, private) for public, private in names]
    return found[0], found[1], found[2]


class _Batch:
    """The per-loop warm starts of the MPC's solver and the batched solve of one step."""

    def __init__(self, mpc: ParametricMPC, theta: np.ndarray, n: int) -> None:
        self.mpc, self.theta = mpc, theta
        self.problem, self.kkt, self.solver = _parts(mpc)
        self.prev: list[dict | None] = [None] * n

    def solve(self, loops: np.ndarray, X: np.ndarray) -> list[MPCSolution | Exception]:
        """The solve at the states ``X`` (m, nx) of ``loops`` (m,): Newton steps together,
        the others alone; each solution with its share of the batch's time (or the exception
        the loop's own solve raised)."""
        t0 = time.perf_counter()
        sv = self.solver
        P = np.hstack([X, np.broadcast_to(self.theta, (len(loops), len(self.theta)))])
        warm = [j for j, i in enumerate(loops) if sv.warm_start and self.prev[i] is not None]
        found = self.newton([self.prev[loops[j]] for j in warm], P[warm]) if sv.newton_steps else []
        sols: list[MPCSolution | Exception | None] = [None] * len(loops)
        for j, hit in zip(warm, found):
            if hit is None:
                continue
            out, w, mult = self.kkt.solver_outputs(*hit[:2])
            sols[j] = sv.solution(X[j], P[j], out, w, "Newton_Succeeded", hit[2], mult, False)
            self.prev[loops[j]] = sv.prev
        shared = (time.perf_counter() - t0) / len(loops)
        for j, i in enumerate(loops):
            if sols[j] is not None:
                sols[j].solve_time = shared  # type: ignore[union-attr]  # set above
                continue
            sv.prev = self.prev[i]  # the loop's own solve from its own warm start
            try:
                sols[j] = self.mpc.solve(X[j], self.theta, sensitivities=False)
            except Exception as err:  # noqa: BLE001 - that loop fails, the others run on
                sols[j] = err
            self.prev[i] = sv.prev
        return sols  # type: ignore[return-value]  # every entry is set

    def newton(self, prevs: list[dict | None], P: np.ndarray) -> list[tuple | None]:
        """The solver's Newton path (``Solver.newton``) for each warm start in ``prevs`` with
        its parameters in ``P``: (y, f, steps) at a converged point, else None."""
        kkt, sv, m = self.kkt, self.solver, len(prevs)
        result: list[tuple | None] = [None] * m
        if m == 0:
            return result
        Y = np.empty((m, kkt.ny))
        ok = np.zeros(m, bool)
        for j, prev in enumerate(prevs):
            w = prev["w_shift"]  # type: ignore[index]  # warm loops only
            lam, mu = kkt.multipliers(w, prev["lam_g"], prev["lam_x"])  # type: ignore[index]
            Y[j] = np.concatenate([w, lam, mu])
            ok[j] = bool(np.all(mu > 0))
        rows = np.flatnonzero(ok)  # the loops still taking steps
        for k in range(1, sv.newton_steps + 1):
            if rows.size == 0:
                break
            call = mapped(kkt.newton, rows.size)
            y_next, *scalars = call(Y[rows].ravel(), P[rows].ravel())
            res0, res, f, h_max, mu_min, h0_max = (_columns(v, rows.size)[:, 0] for v in scalars)
            good = (h0_max < 0) & (h_max < 0) & (mu_min > 0) & np.isfinite(res)
            Y[rows[good]] = _columns(y_next, rows.size)[good]
            done = good & (res <= sv.tol)
            for r, f_r in zip(rows[done], f[done]):
                result[int(r)] = (Y[r].copy(), float(f_r), k)
            stop = (k == sv.newton_steps) | ((k >= 2) & (res > 0.1 * res0))
            rows = rows[good & ~done & ~stop]
        return result


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
    e = None if noise is None else np.asarray(noise, float)
    if e is not None and e.shape != (steps, system.nu):
        raise ValueError(f"noise must be ({steps}, {system.nu}), got {e.shape}")
    if e is not None and not np.all(np.isfinite(e)):
        raise ValueError("the exploration noise contains NaN or inf")
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
            _step(system, batch, out, loops, X, k, steps, p, e)
    finally:
        mpc.reset()
    return out


def _step(
    system: System,
    batch: _Batch,
    out: list,
    loops: np.ndarray,
    X: np.ndarray,
    k: int,
    steps: int,
    p: np.ndarray,
    noise: np.ndarray | None,
) -> None:
    """Step ``k`` of the running ``loops``: record x_k, solve, apply the inputs to the plant
    (``X`` becomes x_{k+1}); a loop whose plant diverges gets its ``PlantDiverged``."""
    for j, sol in enumerate(batch.solve(loops, X[loops])):
        rec = out[loops[j]]
        if isinstance(sol, Exception):
            out[loops[j]] = sol
            continue
        rec.x[k] = X[loops[j]]
        _record_solve(rec, k, sol, False)
        if k < steps:
            u = sol.action if noise is None else sol.action + noise[k]
            rec.u[k] = system.clip_input(u)
    loops = np.array([i for i in loops if isinstance(out[i], EpisodeRecord)], int)
    if k == steps or loops.size == 0:
        return
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
            stopped = f"the plant diverged at step {k}: state {x}"
        elif np.any(far[j]):
            names = ", ".join(nm for nm, f in zip(system.state_names, far[j]) if f)
            stopped = (
                f"the plant ran away at step {k}: state {x} ({names} more than {RUNAWAY:g} "
                "x_scale from x_ref); the episode is stopped"
            )
        else:
            continue
        out[i] = PlantDiverged(stopped, k, float(np.sum(out[i].violation[: k + 1])))
