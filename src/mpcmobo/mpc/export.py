"""The tuned MPC taken out of mpcmobo: a CasADi function, or generated C with a header.

:func:`controller_function` is the MPC of eq. V0 with theta fixed as one CasADi function,

    controller(x, warm, cold) -> (u, warm_next),

``x`` the measured state, ``u`` the first input of the solution (eq. Policy). ``warm`` is the
previous call's ``warm_next`` (the solution's decision vector): IPOPT starts from it shifted by
one stage; with ``cold = 1`` it starts from the cold guess instead, which is what
:meth:`~mpcmobo.mpc.ParametricMPC.solve` does after a reset (the same solver, options and
numbers). Where IPOPT does not converge the function fails (a ``RuntimeError`` in Python, a
non-zero return in C) and the caller applies its own fallback, as the MPC in mpcmobo applies the
previous plan. :func:`export_casadi` saves it (``Function.save``, loaded by ``casadi.Function.load``
with the IPOPT of CasADi's wheel); :func:`export_c` generates its C code (CasADi's code
generator; the solver is IPOPT, linked from the wheel), a header and an example ``main.c`` that
reads states from the standard input and prints the inputs, and :func:`c_compile_command` is
the command that builds it.
"""

from __future__ import annotations

import contextlib
import os
import sys
import sysconfig
from collections.abc import Iterator
from pathlib import Path

import casadi as ca
import numpy as np

from mpcmobo.mpc.codegen import compiler_command
from mpcmobo.mpc.embedded_source import READ_STATE_C
from mpcmobo.mpc.parametric import ParametricMPC

__all__ = [
    "ExportError",
    "c_compile_command",
    "check_generated",
    "controller_function",
    "controller_inputs",
    "export_c",
    "export_casadi",
]

NAME = "controller"


def controller_function(mpc: ParametricMPC, theta: np.ndarray | None = None) -> ca.Function:
    """The MPC with ``theta`` (default theta0) as ``controller(x, warm, cold) -> (u,
    warm_next)`` (module docstring)."""
    theta = mpc.check_theta(theta)
    pr = mpc.problem
    x = ca.MX.sym("x", mpc.nx)
    warm = ca.MX.sym("warm", pr.nw)
    cold = ca.MX.sym("cold")
    guess = ca.MX.zeros(pr.nw)  # the cold guess: every predicted state at x (scaled)
    zx = (x - ca.DM(mpc.system.x_ref)) / ca.DM(pr.Sx)
    for idx in pr.ix:
        guess[idx] = zx
    shifted = warm[pr.wshift.tolist()]
    w0 = ca.if_else(cold > 0.5, guess, shifted)
    p = ca.vertcat(x, ca.DM(theta))
    options = {**mpc.solver.cold_options, "error_on_fail": True}
    solver = ca.nlpsol(f"{NAME}_ipopt", "ipopt", pr.nlp, options)
    sol = solver(x0=w0, p=p, lbx=pr.lbw, ubx=pr.ubw, lbg=pr.lbg, ubg=pr.ubg)
    w = sol["x"]
    u = ca.DM(mpc.system.u_ref) + ca.DM(pr.Su) * w[list(pr.iu[0])]
    return ca.Function(NAME, [x, warm, cold], [u, w], ["x", "warm", "cold"], ["u", "warm_next"])


def controller_inputs(
    mpc: ParametricMPC, theta: np.ndarray | None, states: np.ndarray
) -> list[np.ndarray]:
    """The inputs :func:`controller_function` gives at ``states`` (rows, in order) called as
    its users call it: cold at the first, then warm from the last solution it returned; a row
    of NaN where it fails (the caller's fallback applies). After a failure the next call starts
    from the last solution (the first array) or cold (the second, there only where a call
    failed: else it is the first). CasADi's report of a failed call (its inputs, on the
    standard error) is not shown."""
    controller = controller_function(mpc, theta)
    chains = [_chain(controller, states, mpc.system.nu, cold_after_failure=False)]
    if np.isnan(chains[0]).any():
        chains.append(_chain(controller, states, mpc.system.nu, cold_after_failure=True))
    return chains


def _chain(
    controller: ca.Function, states: np.ndarray, nu: int, cold_after_failure: bool
) -> np.ndarray:
    """One pass of :func:`controller_inputs`."""
    warm = np.zeros(controller.size1_in(1))
    out = np.full((len(states), nu), np.nan)
    cold = True
    with _quiet_stderr():
        for k, x in enumerate(np.asarray(states, float)):
            try:
                u, w = controller(x, warm, 1.0 if cold else 0.0)
            except RuntimeError:  # IPOPT did not converge (error_on_fail)
                cold = cold or cold_after_failure
                continue
            out[k] = np.asarray(u, float).reshape(-1)
            warm, cold = np.asarray(w, float).reshape(-1), False
    return out


@contextlib.contextmanager
def _quiet_stderr() -> Iterator[None]:
    """The process's standard error (file descriptor 2, where CasADi's C++ writes) discarded."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


class ExportError(ValueError):
    """An MPC that cannot be taken out in the format asked: the message says why."""


# what to do where CasADi cannot serialise or generate a function of the system's equations
NOT_EXPRESSIONS = (
    "write the system's equations in CasADi expressions (casadi.if_else, fmin, fmax, "
    "interpolant, ...): a Python casadi.Callback runs in mpcmobo but cannot be exported"
)


def export_casadi(mpc: ParametricMPC, theta: np.ndarray | None, path: str | os.PathLike) -> Path:
    """Save :func:`controller_function` to ``path`` (a ``.casadi`` file), loaded once to
    check it (an :class:`ExportError` where it cannot be: the file is removed)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    controller_function(mpc, theta).save(str(path))
    try:
        ca.Function.load(str(path))
    except RuntimeError as err:
        path.unlink(missing_ok=True)
        found = str(err).strip().splitlines()[-1][:200]
        raise ExportError(
            f"the controller cannot be saved as a CasADi function ({found}): {NOT_EXPRESSIONS}"
        ) from None
    return path


def check_generated(source: Path, written: list[Path]) -> None:
    """An :class:`ExportError` (the ``written`` files removed) where CasADi's generated
    ``source`` holds an ``#error`` (a function it cannot generate code for)."""
    lines = source.read_text().splitlines()
    found = [line.strip() for line in lines if line.lstrip().startswith("#error")]
    if not found:
        return
    for path in written:
        path.unlink(missing_ok=True)
    raise ExportError(
        f"CasADi cannot generate C for the controller ({found[0][7:].strip()[:200]}): "
        f"{NOT_EXPRESSIONS}"
    )


#: what :func:`quiet_unused` puts before CasADi's generated C: its functions share one
#: signature and many leave a parameter unused, which GCC and Clang would report one by one in
#: a build with ``-Wextra``
QUIET_UNUSED = (
    "/* generated functions share one signature: not every one uses each parameter */\n"
    "#if defined(__GNUC__)\n"
    '#pragma GCC diagnostic ignored "-Wunused-parameter"\n'
    "#endif\n"
)


def quiet_unused(source: Path) -> None:
    """Prepend :data:`QUIET_UNUSED` to CasADi's generated ``source``, so that a build with
    ``-Wall -Wextra -pedantic`` compiles it without a warning."""
    source.write_text(QUIET_UNUSED + source.read_text())


def _casadi_dir() -> Path:
    return Path(ca.__file__).resolve().parent


MAIN_C = (
    r"""/* Example: the tuned MPC in closed loop with your own code.
 * Reads one state per line (NX numbers separated by spaces or tabs; empty lines are skipped)
 * from stdin, prints the input (NU numbers). A line that is not NX numbers stops it with exit
 * code 2, naming the line; a failed solve with exit code 1.
 * The first call starts cold; each later one warm-starts from the previous solution. */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include "controller.h"

"""
    + READ_STATE_C
    + r"""
int main(int argc, char** argv) {
  casadi_int sz_arg, sz_res, sz_iw, sz_w;
  char line[4096];
  int got, n = 0;
  if (argc > 1) {
    fprintf(argc == 2 && strcmp(argv[1], "--help") == 0 ? stdout : stderr,
            "usage: %s < states (one state per line: %d numbers)\n", argv[0], NX);
    return argc == 2 && strcmp(argv[1], "--help") == 0 ? 0 : 2;
  }
  controller_work(&sz_arg, &sz_res, &sz_iw, &sz_w);
  const casadi_real** arg = malloc(sz_arg * sizeof(casadi_real*));
  casadi_real** res = malloc(sz_res * sizeof(casadi_real*));
  casadi_int* iw = malloc(sz_iw * sizeof(casadi_int));
  casadi_real* w = malloc(sz_w * sizeof(casadi_real));
  casadi_real x[NX], warm[NW] = {0}, u[NU], cold = 1;
  int mem = controller_checkout();
  while (fgets(line, sizeof line, stdin)) {
    n++;
    got = read_state(line, x, NX);  /* casadi_real is double */
    if (got == 0) continue;
    if (got < 0 || (!strchr(line, '\n') && !feof(stdin))) {
      fprintf(stderr, "line %d: a state is %d numbers separated by spaces, one state per line\n",
              n, NX);
      return 2;
    }
    arg[0] = x; arg[1] = warm; arg[2] = &cold;
    res[0] = u; res[1] = warm;  /* the solution becomes the next warm start */
    if (controller(arg, res, iw, w, mem)) { fprintf(stderr, "solver failed\n"); return 1; }
    for (int i = 0; i < NU; i++) printf(i ? " %.17g" : "%.17g", u[i]);
    printf("\n");
    cold = 0;
  }
  controller_release(mem);
  return 0;
}
"""
)


def export_c(mpc: ParametricMPC, theta: np.ndarray | None, directory: str | os.PathLike) -> Path:
    """Generate ``controller.c``, ``controller.h`` and ``main.c`` into ``directory`` (made if
    missing); returns the directory. Build with :func:`c_compile_command`."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    fn = controller_function(mpc, theta)
    gen = ca.CodeGenerator(f"{NAME}.c", {"with_header": True})
    gen.add(fn)
    gen.generate(str(directory) + os.sep)
    check_generated(directory / f"{NAME}.c", [directory / f"{NAME}.c", directory / f"{NAME}.h"])
    quiet_unused(directory / f"{NAME}.c")
    sizes = f"#define NX {mpc.nx}\n#define NU {mpc.nu}\n#define NW {mpc.problem.nw}\n"
    header = directory / f"{NAME}.h"
    header.write_text(header.read_text() + "\n" + sizes)
    (directory / "main.c").write_text(MAIN_C)
    return directory


def c_compile_command(directory: str | os.PathLike, output: str = "controller") -> list[str]:
    """The command that compiles the generated code of ``directory`` with the example
    ``main.c`` into the program ``output``, linked to the IPOPT of CasADi's wheel."""
    d = Path(directory)
    lib = _casadi_dir()
    return [
        *compiler_command(),
        "-O1",
        str(d / f"{NAME}.c"),
        str(d / "main.c"),
        f"-I{lib / 'include'}",
        f"-I{sysconfig.get_paths()['include']}",
        f"-L{lib}",
        "-lipopt",
        f"-Wl,-rpath,{lib}",
        "-lm",
        "-o",
        str(d / output),
    ]
