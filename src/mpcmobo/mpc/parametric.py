"""The parametric MPC of a system, built once and solved many times, and the parts it composes.

:class:`ParametricMPC` checks the options and the inputs and builds the pipeline of one MPC:

- :mod:`mpcmobo.mpc.transcription`: the optimal control problem as an NLP in scaled variables,
  and the layout of its decision vector;
- :mod:`mpcmobo.mpc.kkt`: the NLP's barrier-relaxed KKT residual, the sensitivities of the
  policy and the value, and the Newton step of warm solves;
- :mod:`mpcmobo.mpc.codegen` (option ``codegen``): those functions as compiled C, cached;
- :mod:`mpcmobo.mpc.solve`: the solve paths (Newton steps, the interior-point continuation of
  :mod:`mpcmobo.mpc.interior`, IPOPT warm and cold, the fallback input) and their result,
  :class:`~mpcmobo.mpc.solve.MPCSolution`.

The parts are public attributes of the MPC: ``mpc.problem`` (the
:class:`~mpcmobo.mpc.transcription.Transcription`: sizes, scales, layout of ``w``), ``mpc.kkt``
(the :class:`~mpcmobo.mpc.kkt.KKTSystem`) and ``mpc.solver`` (the
:class:`~mpcmobo.mpc.solve.Solver`: its paths and the warm start ``solver.prev``). A test that
injects a failure replaces one of the solver's public path methods on the instance
(``monkeypatch.setattr(mpc.solver, "ipopt", ...)``).
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Literal

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from mpcmobo.mpc.codegen import compiled_library, compiler_available
from mpcmobo.mpc.interior import Continuation
from mpcmobo.mpc.kkt import KKTSystem
from mpcmobo.mpc.solve import MPCSolution, Solver
from mpcmobo.mpc.transcription import Transcription
from mpcmobo.systems.base import System
from mpcmobo.systems.parameterization import Parameterization


class ParametricMPC:
    """The MPC of eq. (V0) for a :class:`~mpcmobo.systems.System`, built once, solved many times.

    ``ParametricMPC(system, model="imperfect", **options)`` is the way to build the MPC of a
    system.

    Parameters
    ----------
    system:
        The system whose model, bounds, references and parameterization are used.
    model:
        ``"imperfect"``, ``"perfect"``, another name in ``system.models`` or a parameter vector.
    horizon, gamma:
        Prediction horizon N and discount (default: the system's ``mpc_spec``).
    tau:
        Barrier parameter at which the problem is solved and differentiated (scaled units).
    tol:
        IPOPT tolerance on the barrier problem, and the Newton steps' acceptance test.
    max_iter:
        IPOPT's iteration limit (the warm-started solver: at most 50).
    warm_start:
        Initialise each solve from the shifted previous solution.
    solver_options:
        Extra IPOPT options (``{"max_iter": 200}``, ...), for the cold and the warm solver.
    cost_scale:
        The cost is divided by it (default: the mean reference weight in scaled units).
    warm_options:
        IPOPT options of the warm-started solver only (after the built-in warm-start settings).
    linsol:
        CasADi linear solver plugin of the sensitivity system (``"qr"``, the default and
        fastest measured, ``"csparse"``, ...), used in one adjoint solve inside a single CasADi
        function.
    codegen:
        Use generated C code for IPOPT's NLP functions, the sensitivity function and the Newton
        step, compiled once per machine and problem and cached on disk (``mpcmobo.mpc.codegen``):
        the first build compiles (tens of seconds), later builds of the same problem load the
        library. Same numbers as without it, faster steps (``docs/benchmarks.md``, step time).
        Needs a C compiler (``$CC`` or ``cc``). ``"auto"``: compiled where a C compiler is
        found and compiles the code, else CasADi's virtual machine (with a warning where the
        compiler fails); ``build_info["codegen"]`` says which.
    cache_dir:
        Directory of the compiled libraries (default: ``mpcmobo.mpc.codegen.cache_directory()``).
    newton_steps:
        With a warm start, first try at most this many Newton steps on the barrier KKT system
        ``R(y, p) = 0`` from the shifted previous solution (fraction-to-boundary steps that keep
        ``H < 0`` and ``mu > 0``). Accepted only when ``|R|_inf <= tol`` at a strictly interior
        point: then it is the barrier solution IPOPT stops at, to its tolerance; otherwise IPOPT
        solves as without it. 0: no Newton steps.
    continuation_steps:
        When the Newton steps cannot start or do not converge, at most this many steps of the
        interior-point continuation of :mod:`mpcmobo.mpc.interior` on the same Newton system
        (re-centred shifted plan, barrier parameter 1e-3 down to ``tau``), and without a warm
        start as many from the cold guess, each accepted by the same test and only at a
        minimum; IPOPT solves where they do not get there. On the CSTR IPOPT then solves a few
        percent of the closed-loop steps instead of 43%, and a study runs in half the time
        (docs/benchmarks.md); on a few states the path ends at another local minimum than
        IPOPT's from the same warm start. 0: IPOPT right away.

    Attributes
    ----------
    problem, kkt, solver:
        The parts: the transcription, the KKT system and the solve paths (module docstring).
    N, gamma, tau, warm_start:
        The horizon, discount, barrier parameter and warm-start switch (read only).
    """

    def __init__(
        self,
        system: System,
        model: str | np.ndarray = "imperfect",
        *,
        horizon: int | None = None,
        gamma: float | None = None,
        tau: float = 1e-6,
        tol: float = 1e-8,
        max_iter: int = 150,
        warm_start: bool = True,
        solver_options: dict | None = None,
        cost_scale: float | None = None,
        warm_options: dict | None = None,
        linsol: str = "qr",
        codegen: bool | Literal["auto"] = False,
        cache_dir: str | os.PathLike | None = None,
        newton_steps: int = 6,
        continuation_steps: int = 30,
    ) -> None:
        spec = system.mpc_spec
        self.system = system
        self.model = model if isinstance(model, str) else "custom"
        self.model_params = np.array(system.model_params(model), dtype=float)
        N = int(spec.horizon if horizon is None else horizon)
        gamma = float(spec.gamma if gamma is None else gamma)
        _check_options(N, gamma, tau, linsol, newton_steps, continuation_steps)
        self.param: Parameterization = system.parameterization
        self.theta0 = self.param.theta0.copy()
        if "model" in self.param.blocks:  # learnable model parameters: this MPC's own model
            idx = list(self.param.model_param_index)
            self.theta0[self.param.blocks["model"]] = self.model_params[idx]
        self.theta_names = list(self.param.names)
        self.n_theta = self.param.n_theta
        self.nx, self.nu = system.nx, system.nu
        self.problem = Transcription(
            system, self.model_params, self.param, horizon=N, gamma=gamma, cost_scale=cost_scale
        )
        self.kkt = KKTSystem(self.problem, tau, linsol)
        #: how the MPC's functions were built: {"codegen", and with it "path", "cached", "seconds"}
        self.build_info: dict = {"codegen": False}
        nlp: dict | str = self.problem.nlp
        lib = self._library(codegen, cache_dir)
        if lib is not None:
            self.build_info["codegen"] = True
            nlp = str(lib)
            self.kkt.load(lib)
        self.solver = Solver(
            self.problem,
            self.kkt,
            nlp,
            tol=tol,
            max_iter=max_iter,
            newton_steps=int(newton_steps),
            warm_start=warm_start,
            solver_options=solver_options,
            warm_options=warm_options,
            interior=Continuation(max_steps=int(continuation_steps))
            if continuation_steps
            else None,
        )

    def _library(
        self, codegen: bool | Literal["auto"], cache_dir: str | os.PathLike | None
    ) -> Path | None:
        """The compiled library the MPC's functions come from (None: CasADi's virtual machine):
        ``codegen`` True compiles or fails, ``"auto"`` compiles where it can."""
        if codegen == "auto":
            if not compiler_available():
                return None
            try:
                return self._compiled_library(cache_dir)
            except RuntimeError as err:
                warnings.warn(
                    f'the MPC runs without generated code ([mpc] codegen = "auto"): {err}',
                    RuntimeWarning,
                    stacklevel=3,
                )
                return None
        if codegen not in (True, False):
            raise ValueError(f"codegen must be true, false or 'auto', got {codegen!r}")
        return self._compiled_library(cache_dir) if codegen else None

    def _compiled_library(self, cache_dir: str | os.PathLike | None) -> Path:
        """The NLP functions IPOPT calls, the sensitivity function and the Newton step,
        compiled (or loaded from the cache)."""
        nlp_dict = self.problem.nlp
        nlp = ca.Function(
            "nlp",
            [nlp_dict["x"], nlp_dict["p"]],
            [nlp_dict["f"], nlp_dict["g"]],
            ["x", "p"],
            ["f", "g"],
        )
        probe = ca.nlpsol("probe", "ipopt", nlp_dict, {"calc_lam_p": True})
        names = ("nlp_f", "nlp_g", "nlp_grad_f", "nlp_jac_g", "nlp_hess_l", "nlp_grad")
        kkt = self.kkt
        functions = [nlp, *(probe.get_function(n) for n in names), kkt.sens, kkt.newton]
        functions += [kkt.newton_mu, kkt.rows, kkt.reduced_hessian]
        return compiled_library(functions, directory=cache_dir, info=self.build_info)

    @property
    def N(self) -> int:
        """The prediction horizon."""
        return self.problem.N

    @property
    def gamma(self) -> float:
        """The discount factor."""
        return self.problem.gamma

    @property
    def tau(self) -> float:
        """The barrier parameter at which the MPC is solved and differentiated."""
        return self.kkt.tau

    @property
    def warm_start(self) -> bool:
        """Whether each solve starts from the shifted previous solution."""
        return self.solver.warm_start

    def check_theta(self, theta: ArrayLike | None) -> np.ndarray:
        """``theta`` as a float vector of length ``n_theta`` (None: theta0); a wrong shape or a
        non-finite value is a ``ValueError``."""
        if theta is None:
            return self.theta0.copy()
        theta = np.asarray(theta, dtype=float)
        if theta.ndim != 1 or theta.shape[0] != self.n_theta:
            raise ValueError(
                f"theta has shape {theta.shape}, expected ({self.n_theta},): {self.theta_names}"
            )
        if not np.all(np.isfinite(theta)):
            raise ValueError(f"theta contains NaN or inf: {theta}")
        return theta

    def reset(self) -> None:
        """Forget the warm start (call between episodes)."""
        self.solver.reset()

    def fallback_action(self) -> np.ndarray:
        """The safe input used when a solve fails: the shifted previous plan, else ``u_r``."""
        return self.solver.fallback_action()

    def solve(
        self,
        x: ArrayLike,
        theta: ArrayLike | None = None,
        sensitivities: bool = True,
        *,
        newton: bool = True,
    ) -> MPCSolution:
        """Solve eq. (V0) at state ``x``; return pi_theta(x), V_theta(x) and their gradients
        (``sensitivities``), by the paths of :mod:`mpcmobo.mpc.solve` (``newton=False``:
        without the Newton steps, for a caller that took them already and saw them fail)."""
        x = self.system.check_state(x)
        theta = self.check_theta(theta)
        return self.solver.solve(x, theta, sensitivities, newton=newton)


def _check_options(
    horizon: int, gamma: float, tau: float, linsol: str, newton_steps: int, continuation: int
) -> None:
    if horizon < 1:
        raise ValueError(f"horizon must be at least 1, got {horizon}")
    if not 0 < gamma <= 1:
        raise ValueError(f"gamma must be in (0, 1], got {gamma}")
    if tau <= 0:
        raise ValueError(f"tau must be positive, got {tau}")
    if not ca.has_linsol(linsol):
        raise ValueError(f"linsol '{linsol}' is not a linear solver plugin of this CasADi")
    _check_count("newton_steps", newton_steps)
    _check_count("continuation_steps", continuation)


def _check_count(name: str, value: int) -> None:
    if int(value) != value or value < 0:
        raise ValueError(f"{name} must be an integer >= 0, got {value}")
