"""The structured path of warm solves: fatrop on the same NLP, polished by the Newton steps.

fatrop (the interior-point solver for optimal control problems that CasADi ships) factorises
the KKT system stage by stage, with the Riccati recursion. CasADi hands it the stages when its
structure detection (``structure_detection="auto"``) sees the decision variables stage by stage
(each stage's state, then its controls) and, before each stage's other constraints, its
gap-closing constraints ``x_{k+1} - F(x_k, u_k) = 0`` with the coefficient +1 on ``x_{k+1}``.
The transcription's ``w`` is already in that order (``eta_i, u_i, x_{i+1}``: the slacks and
inputs are a stage's controls); :class:`Stagewise` reorders the rows of ``g = [G; H]`` (stage
``i``: its model rows, negated, since the transcription writes ``(F - x_{i+1}) / S_x``, then its
relaxed state bounds; the last stage's bounds at the end) and maps fatrop's multipliers back.

fatrop has no barrier target (IPOPT's ``mu_target``) and no dual warm start: it stops at its
tolerance with a barrier parameter near 0, where a simple bound can be violated by about 1e-8.
:func:`interior_start` moves that point into the interior (a variable at its bound to a centred
distance from it, the rows relaxed by a slack by :func:`~mpcmobo.mpc.interior.recentre`), and
the Newton steps of the barrier KKT system (:meth:`mpcmobo.mpc.solve.Solver.newton`) take it to
the root IPOPT stops at: the same policy and sensitivities, where both reach the same local
optimum (from the same warm start they can reach different ones; ``docs/benchmarks.md``).

fatrop (1.1.8, the wheel's) has no bound on its inertia correction: once its KKT matrix holds a
number that is not finite, it raises the regularisation forever and never returns. The model's
equations produce such numbers far outside the state box (the CSTR's concentration at ten times
its reference, 2.4 widths of its box above it, overflows the model's exponential), so a state
further than :data:`REACH` widths of its box outside it (:func:`within_reach`) is not handed to
fatrop: IPOPT solves it, and stops with an error where the model cannot be evaluated.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from mpcmobo.mpc.interior import Continuation, recentre
from mpcmobo.mpc.kkt import KKTSystem
from mpcmobo.mpc.transcription import Transcription

#: how far outside its box (in widths of the box) a state may be for fatrop to solve from it
REACH = 1.0

#: CasADi's options of the fatrop solver besides its structure (no lam_p: the sensitivities
#: come from the KKT system; no bound consistency: it would put variables on their bounds)
FATROP_OPTIONS = {
    "print_time": False,
    "show_eval_warnings": False,
    "calc_lam_p": False,
    "bound_consistency": False,
}


def within_reach(lb: np.ndarray, ub: np.ndarray, x: np.ndarray) -> bool:
    """Whether every state of ``x`` is finite and, where its box ``[lb, ub]`` is finite, at
    most :data:`REACH` widths of the box outside it (module docstring)."""
    x, lb, ub = (np.asarray(v, float) for v in (x, lb, ub))
    if not np.all(np.isfinite(x)):
        return False
    width = np.where(np.isfinite(ub - lb), ub - lb, np.inf)
    return bool(np.all((x >= lb - REACH * width) & (x <= ub + REACH * width)))


class Stagewise:
    """The NLP of a :class:`~mpcmobo.mpc.transcription.Transcription` with its constraint rows
    in fatrop's stage order: ``nlp`` (CasADi's ``nlpsol`` dictionary), ``equality`` (the rows
    that are equalities, CasADi's ``equality`` option), ``lbg``, ``ubg``; ``perm``: the original
    row of each new row, ``sign``: -1 on the model rows (negated)."""

    def __init__(self, problem: Transcription) -> None:
        N, nx, neq, nin = problem.N, problem.nx, problem.neq, problem.nin
        eq = np.arange(neq).reshape(N, nx)
        ineq = neq + np.arange(nin).reshape(N + 1, nin // (N + 1))
        blocks = [np.concatenate([eq[i], ineq[i]]) for i in range(N)] + [ineq[N]]
        self.perm = np.concatenate(blocks)
        self.sign = np.where(self.perm < neq, -1.0, 1.0)
        g = ca.vertcat(problem.geq, problem.gin)
        rows = [g[int(r)] if s > 0 else -g[int(r)] for r, s in zip(self.perm, self.sign)]
        self.nlp = {"x": problem.w, "p": problem.p, "f": problem.f, "g": ca.vertcat(*rows)}
        self.equality = [bool(r < neq) for r in self.perm]
        # the negated rows are the model's, with lbg = ubg = 0: the bounds only move
        self.lbg, self.ubg = problem.lbg[self.perm], problem.ubg[self.perm]

    def original_multipliers(self, lam: np.ndarray) -> np.ndarray:
        """The multipliers of ``g`` in the transcription's order from those of the rows here."""
        out = np.empty_like(lam)
        out[self.perm] = self.sign * lam
        return out

    def options(self, tol: float, max_iter: int, extra: dict | None = None) -> dict:
        """The options of CasADi's fatrop solver of this NLP: structure detection, fatrop's
        tolerance ``tol`` and iteration limit ``max_iter``, then ``extra`` fatrop options."""
        fatrop = {"print_level": 0, "tol": tol, "max_iter": max_iter, **(extra or {})}
        return {
            **FATROP_OPTIONS,
            "structure_detection": "auto",
            "equality": self.equality,
            "fatrop": fatrop,
        }


def interior_start(
    kkt: KKTSystem,
    w: np.ndarray,
    lam_g: np.ndarray,
    lam_x: np.ndarray,
    p: np.ndarray,
    delta: float = 1e-2,
) -> np.ndarray | None:
    """A strictly interior start ``y = (w, lambda, mu)`` of the Newton steps at the barrier
    parameter ``tau`` from a solution of the NLP without it (``w`` and CasADi's multipliers):
    a variable within ``1e-3 tau`` of a bound (or beyond it) moves to ``tau / z`` inside it
    (``z``: its bound's multiplier; between ``1e-2 tau`` and ``delta``), then the relaxed rows are
    re-centred at the barrier parameter ``tau`` (:func:`~mpcmobo.mpc.interior.recentre`). None
    when a row that no slack relaxes stays on or beyond its bound."""
    tau, gap = kkt.tau, 1e-3 * kkt.tau
    lam, mu = kkt.multipliers(w, lam_g, lam_x)
    w = w.copy()
    lbw, ubw = kkt.problem.lbw, kkt.problem.ubw
    n_lb = len(kkt.lb_idx)
    for idx, z, side in (
        (kkt.lb_idx, mu[kkt.nin : kkt.nin + n_lb], 1.0),
        (kkt.ub_idx, mu[kkt.nin + n_lb :], -1.0),
    ):
        bound = lbw[idx] if side > 0 else ubw[idx]
        inside = side * (w[idx] - bound)
        offset = np.clip(tau / np.maximum(z, 1e-300), 1e-2 * tau, delta)
        w[idx] = np.where(inside < gap, bound + side * offset, w[idx])
    return recentre(kkt, w, lam, mu, p, Continuation(m0=tau, delta=delta))


class Fatrop:
    """fatrop on the :class:`Stagewise` NLP of ``kkt``'s transcription (``nlp``: its
    dictionary, or the path of a compiled library that holds its functions), with fatrop's
    tolerance ``tol`` and at most ``max_iter`` iterations. :meth:`solve` returns the interior
    start of the Newton steps that polish its solution."""

    def __init__(
        self,
        kkt: KKTSystem,
        stagewise: Stagewise,
        nlp: dict | str,
        *,
        tol: float,
        max_iter: int,
        options: dict | None = None,
    ) -> None:
        self.kkt, self.stagewise, self.max_iter = kkt, stagewise, int(max_iter)
        opts = stagewise.options(tol, max_iter, options)
        self.solver = ca.nlpsol("mpc_fatrop", "fatrop", nlp, opts)

    def solve(self, w0: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, int] | None:
        """fatrop from the primal guess ``w0`` at ``p``: (the interior start ``y`` of the
        polishing Newton steps, fatrop's iterations), or None when fatrop fails or raises."""
        pr, sw = self.kkt.problem, self.stagewise
        try:
            out = self.solver(x0=w0, p=p, lbx=pr.lbw, ubx=pr.ubw, lbg=sw.lbg, ubg=sw.ubg)
        except RuntimeError:  # an evaluation error fatrop did not recover from
            return None
        st = self.solver.stats()
        w = np.asarray(out["x"]).reshape(-1)
        if not (st.get("success", False) and np.all(np.isfinite(w))):
            return None
        lam_g = sw.original_multipliers(np.asarray(out["lam_g"]).reshape(-1))
        lam_x = np.asarray(out["lam_x"]).reshape(-1)
        y = interior_start(self.kkt, w, lam_g, lam_x, p)
        return None if y is None else (y, int(st.get("iter_count", 0)))
