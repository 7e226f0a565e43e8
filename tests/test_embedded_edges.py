"""The embedded controller where a user's program meets it at its edges: a strict build
(``-std=c99 -Wall -Wextra -pedantic``) without a warning, a state that is NaN or inf, the
example program's arguments and the lines of its input."""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest

from mpcmobo.mpc import ParametricMPC
from mpcmobo.mpc.codegen import compiler_command
from mpcmobo.mpc.embedded import export_embedded
from mpcmobo.systems import get_system

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")

STRICT = ["-std=c99", "-Wall", "-Wextra", "-pedantic", "-O0"]

# calls controller_step as a control task does: a state, then NaN, then inf, then the state
HARNESS = r"""#include <math.h>
#include <stdio.h>
#include "controller.h"

static void show(const double* x) {
  double u[8];
  int i, r = controller_step(x, u);
  printf("%d %d", r, controller_path());
  for (i = 0; i < controller_nu(); i++) printf(" %.17g", u[i]);
  printf("\n");
}

int main(void) {
  double good[2] = {0.8, -0.3}, nan_[2] = {0.8, -0.3}, inf_[2] = {0.8, -0.3};
  nan_[0] = NAN;
  inf_[1] = INFINITY;
  show(good);
  show(nan_);
  show(inf_);
  show(good);
  return 0;
}
"""


@pytest.fixture(scope="module")
def lq_embedded(tmp_path_factory):
    """The lq MPC's embedded controller, built strictly with main.c and with the harness:
    the directory, the MPC and the compiler's messages."""
    mpc = ParametricMPC(get_system("lq"))
    d = export_embedded(mpc, None, tmp_path_factory.mktemp("emb"))
    (d / "harness.c").write_text(HARNESS)
    objects, messages = [], ""
    for name in ("controller", "mpc_functions", "main", "harness"):
        cmd = [*compiler_command(), *STRICT, "-c", str(d / f"{name}.c"), "-o", str(d / f"{name}.o")]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr
        messages += proc.stderr
        objects.append(str(d / f"{name}.o"))
    for program, main in (("controller", objects[2]), ("harness", objects[3])):
        cmd = [*compiler_command(), *objects[:2], main, "-lm", "-o", str(d / program)]
        subprocess.run(cmd, check=True)
    return d, mpc, messages


def test_a_strict_build_reports_no_warning(lq_embedded):
    """The generated functions leave parameters unused (one signature for all): the build with
    ``-std=c99 -Wall -Wextra -pedantic`` says nothing of it."""
    _, _, messages = lq_embedded
    assert messages == ""


def test_a_state_that_is_not_a_number_gets_the_fallback_input(lq_embedded):
    """A NaN or an infinity in the state (a failed sensor) is not solved: the step returns 1
    with the previous plan's next input, finite and within the bounds, and the next state is
    solved warm from the plan as before, as the MPC solves it."""
    d, mpc, _ = lq_embedded
    out = subprocess.run([str(d / "harness")], capture_output=True, text=True, check=True)
    rows = [line.split() for line in out.stdout.splitlines()]
    codes = [(int(r[0]), int(r[1])) for r in rows]
    u = np.array([[float(v) for v in r[2:]] for r in rows])
    assert codes[0][0] == 0 and codes[1] == (1, 0) and codes[2] == (1, 0)
    assert np.all(np.isfinite(u))
    system = mpc.system
    assert np.all((u >= system.u_lb) & (u <= system.u_ub))
    mpc.reset()
    first = mpc.solve(np.array([0.8, -0.3]), sensitivities=False)
    np.testing.assert_allclose(u[0], first.action, atol=1e-6)
    np.testing.assert_allclose(u[1], first.plan_u[1], atol=1e-6)  # the plan's next input
    np.testing.assert_allclose(u[2], first.plan_u[2], atol=1e-6)
    again = mpc.solve(np.array([0.8, -0.3]), sensitivities=False)  # warm from the first
    assert codes[3][0] == 0
    np.testing.assert_allclose(u[3], again.action, atol=1e-6)


def _main(d, text, *args):
    return subprocess.run(
        [str(d / "controller"), *args], input=text, capture_output=True, text=True
    )


def test_the_example_refuses_an_argument_it_does_not_know(lq_embedded):
    """``-cold`` or ``--colt`` would otherwise run warm without a word: it is refused with
    the usage and exit code 2; ``--help`` prints the usage."""
    d, _, _ = lq_embedded
    for args in (["-cold"], ["--colt"], ["--cold", "states.txt"]):
        proc = _main(d, "0.8 -0.3\n", *args)
        assert proc.returncode == 2 and proc.stdout == "", args
        assert "usage:" in proc.stderr and "[--cold]" in proc.stderr
    helped = _main(d, "", "--help")
    assert helped.returncode == 0 and "one state per line: 2 numbers" in helped.stdout


def test_the_example_reads_one_state_per_line(lq_embedded):
    """A line with a number too many or too few is refused, naming the line, rather than read
    on into the next state; empty lines and Windows line ends pass."""
    d, _, _ = lq_embedded
    for text, line in (("0.8 -0.3 0.1\n0.2\n", 1), ("0.8 -0.3\n0.8\n-0.3\n", 2)):
        proc = _main(d, text)
        assert proc.returncode == 2, text
        assert f"line {line}: a state is 2 numbers separated by spaces" in proc.stderr
    proc = _main(d, "0.8 -0.3\r\n\n0.1\t0.2\r\n", "--cold")
    assert proc.returncode == 0 and len(proc.stdout.splitlines()) == 2


def test_a_fast_math_build_is_refused(lq_embedded):
    """``-ffast-math`` (in ``-Ofast``) lets the compiler drop every check for NaN and inf, the
    NaN state's included: the controller's source refuses such a build, saying why."""
    d, _, _ = lq_embedded
    for flag in ("-Ofast", "-ffast-math"):
        cmd = [*compiler_command(), flag, "-c", str(d / "controller.c"), "-o", str(d / "fast.o")]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        assert proc.returncode != 0 and "without -ffast-math or -Ofast" in proc.stderr, flag
