"""The tuned MPC exported (mpcmobo.mpc.export, mpcmobo export): the CasADi function gives the
MPC's inputs, the generated C compiles and gives them too."""

from __future__ import annotations

import re
import shutil
import subprocess

import casadi as ca
import numpy as np
import pytest
from typer.testing import CliRunner

from mpcmobo.cli import app
from mpcmobo.experiment.plantlog import TunerError
from mpcmobo.mpc import ParametricMPC
from mpcmobo.mpc.codegen import compiler_command
from mpcmobo.mpc.embedded import embedded_compile_command, export_embedded
from mpcmobo.mpc.export import c_compile_command, controller_function, export_c, export_casadi
from mpcmobo.systems import get_system


def _box_states(system, n: int, seed: int = 0) -> np.ndarray:
    """``n`` states drawn uniformly from the system's initial-state box."""
    rng = np.random.default_rng(seed)
    return np.array([system.sample_initial_state(rng) for _ in range(n)])


def test_the_casadi_function_gives_the_mpcs_input_on_100_states(cstr, cstr_mpc, tmp_path):
    """Saved, loaded and called cold, the controller's input equals ParametricMPC.solve's after
    a reset within 1e-6 wherever the MPC's solve succeeds, and it fails where that fails."""
    theta = cstr_mpc.theta0.copy()
    theta[cstr_mpc.theta_names.index("Q_Ca")] *= 2.0  # another theta than theta0
    controller = ca.Function.load(str(export_casadi(cstr_mpc, theta, tmp_path / "c.casadi")))
    nw = controller.size1_in(1)
    checked = 0
    for x in _box_states(cstr, 100):
        cstr_mpc.reset()
        sol = cstr_mpc.solve(x, theta, sensitivities=False)
        if not sol.success:
            with pytest.raises(RuntimeError):
                controller(x, np.zeros(nw), 1)
            continue
        u = np.asarray(controller(x, np.zeros(nw), 1)[0]).ravel()
        np.testing.assert_allclose(u, sol.action, rtol=0, atol=1e-6)
        checked += 1
    assert checked >= 90


def test_the_warm_start_follows_the_closed_loop(tmp_path):
    """Warm-started from its own previous output along a closed loop, the controller's inputs
    stay those of the cold solves (the same solution, from a better start)."""
    lq = get_system("lq")
    mpc = ParametricMPC(lq)
    f = controller_function(mpc)
    x, warm = np.array([0.8, -0.3]), np.zeros(f.size1_in(1))
    for k in range(5):
        u, warm = f(x, warm, 1 if k == 0 else 0)
        u = np.asarray(u).ravel()
        mpc.reset()
        np.testing.assert_allclose(u, mpc.solve(x, sensitivities=False).action, atol=1e-6)
        x = lq.plant_step(x, u)


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")
def test_the_generated_c_compiles_and_gives_the_same_inputs(tmp_path):
    lq = get_system("lq")
    mpc = ParametricMPC(lq, continuation_steps=0)  # IPOPT's solve, as the C code's
    d = export_c(mpc, None, tmp_path / "c")
    assert {p.name for p in d.iterdir()} >= {"controller.c", "controller.h", "main.c"}
    proc = subprocess.run(c_compile_command(d), capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    states = _box_states(lq, 5)
    # main.c warm-starts each state from the previous solution: feed one state per run
    for x in states:
        out = subprocess.run(
            [str(d / "controller")],
            input=" ".join(map(str, x)) + "\n",
            capture_output=True,
            text=True,
            check=True,
        )
        mpc.reset()
        np.testing.assert_allclose(
            np.array(out.stdout.split(), float), mpc.solve(x, sensitivities=False).action, atol=1e-9
        )
    bad = subprocess.run([str(d / "controller")], input=b"0.1,0.2\n", capture_output=True)
    assert bad.returncode == 2 and b"a state is 2 numbers separated by spaces" in bad.stderr


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")
def test_the_generated_c_compiles_strictly_without_a_warning(tmp_path):
    """CasADi's functions share one signature and leave parameters unused: a build with
    ``-std=c99 -Wall -Wextra -pedantic`` says nothing of it."""
    d = export_c(ParametricMPC(get_system("lq")), None, tmp_path / "c")
    flags = [a for a in c_compile_command(d) if a.startswith("-I")]
    strict = ["-std=c99", "-Wall", "-Wextra", "-pedantic", "-fsyntax-only"]
    for name in ("controller.c", "main.c"):
        cmd = [*compiler_command(), *strict, *flags, str(d / name)]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        assert proc.returncode == 0 and proc.stderr == "", proc.stderr


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")
def test_the_c_example_reads_one_state_per_line(tmp_path):
    """The C format's ``main.c`` refuses a line with a number too many or too few, naming it,
    rather than read on into the next state, and an argument (it takes none)."""
    d = export_c(ParametricMPC(get_system("lq"), continuation_steps=0), None, tmp_path / "c")
    subprocess.run(c_compile_command(d), capture_output=True, check=True)
    program = str(d / "controller")
    for text, line in (("0.8 -0.3 0.1\n0.2\n", 1), ("\n0.8 -0.3\n0.8\n-0.3\n", 3)):
        proc = subprocess.run([program], input=text, capture_output=True, text=True)
        assert proc.returncode == 2, text
        assert f"line {line}: a state is 2 numbers separated by spaces" in proc.stderr
    proc = subprocess.run([program, "--cold"], input="0.8 -0.3\n", capture_output=True, text=True)
    assert proc.returncode == 2 and "usage:" in proc.stderr and proc.stdout == ""
    proc = subprocess.run(
        [program], input="0.8 -0.3\r\n\n0.1\t0.2\n", capture_output=True, text=True
    )
    assert proc.returncode == 0 and len(proc.stdout.splitlines()) == 2


def test_the_command_line_exports_a_trial_and_refuses_a_bad_choice(tmp_path):
    runner = CliRunner()
    d = tmp_path / "tun"
    assert runner.invoke(app, ["ask", str(d), "--system", "lq", "-n", "2"]).exit_code == 0
    res = runner.invoke(app, ["export", str(d), "--out", str(tmp_path / "m.casadi")])
    assert res.exit_code == 2 and "is told yet" in " ".join(res.output.split())  # none told
    res = runner.invoke(app, ["export", str(d), "--format", "zip", "--out", str(tmp_path / "x")])
    assert res.exit_code == 2 and "--format must be casadi, c or embedded" in res.output
    (tmp_path / "file").write_text("")
    res = runner.invoke(app, ["export", str(d), "--format", "c", "--out", str(tmp_path / "file")])
    assert res.exit_code == 2 and "is a file; C code goes into a directory" in res.output
    res = runner.invoke(
        app, ["export", str(d), "--format", "embedded", "-o", str(tmp_path / "file")]
    )
    assert res.exit_code == 2 and "is a file; C code goes into a directory" in res.output
    res = runner.invoke(app, ["export", str(d), "--out", str(tmp_path)])
    assert res.exit_code == 2 and "is a directory; the CasADi function is one file" in res.output
    for fmt_ in ("casadi", "c", "embedded"):  # a path under a file: no traceback
        under = tmp_path / "file" / "sub" / "m"
        res = runner.invoke(app, ["export", str(d), "--format", fmt_, "--out", str(under)])
        said = " ".join(res.output.split())
        assert res.exit_code == 2 and f"{tmp_path / 'file'} is a file, not a directory" in said
    res = runner.invoke(app, ["export", str(tmp_path / "nothere"), "--out", str(tmp_path / "y")])
    assert res.exit_code == 2 and "nothere does not exist" in " ".join(res.output.split())
    res = runner.invoke(app, ["export", str(d), "--learner", "bo", "--out", str(tmp_path / "y")])
    assert (
        res.exit_code == 2
        and "holds no job --learner bo; its jobs: --learner mobo --seed 0"
        in (" ".join(res.output.split()))
    )


def test_an_export_does_not_mix_with_another_controllers_files(tmp_path):
    """A C export into a directory that holds files it does not write (another format's, or
    the user's) is refused; into its own earlier export it writes again, the old build gone."""
    from mpcmobo.cli.plant import _write_controller

    mpc = ParametricMPC(get_system("lq"), codegen=False)
    out = tmp_path / "emb"
    _write_controller(mpc, None, "embedded", out, False)
    (out / "controller").write_text("an earlier build")
    _write_controller(mpc, None, "embedded", out, False)
    assert not (out / "controller").exists()
    with pytest.raises(TunerError, match="holds files this export does not write .*mpc_functions"):
        _write_controller(mpc, None, "c", out, False)
    exported = re.findall(
        r"CASADI_SYMBOL_EXPORT \w+ (\w+)\(", (out / "mpc_functions.c").read_text()
    )
    prefixes = ("mpcmobo_", "mpc_functions_")  # the MPC's functions, the file's version
    assert exported and all(name.startswith(prefixes) for name in exported), exported


def test_an_export_without_a_compiler_says_so(tmp_path, monkeypatch):
    """``--compile`` where ``$CC`` names no program: the files are written and the message says
    so, names the compiler and gives the build line (exit code 2), not a traceback."""
    from mpcmobo.cli.plant import _write_controller

    monkeypatch.setenv("CC", "no-such-cc -O1")
    mpc = ParametricMPC(get_system("lq"), codegen=False)
    out = tmp_path / "emb"
    with pytest.raises(TunerError, match="C compiler 'no-such-cc' cannot be run") as err:
        _write_controller(mpc, None, "embedded", out, True)
    assert "set $CC" in str(err.value) and "main.c -lm -o" in str(err.value)
    assert (out / "mpc_functions.c").is_file() and not (out / "controller").exists()


OWN_PATHS = {
    "Newton_Succeeded",
    "Continuation_Succeeded",
    "Restart_Continuation_Succeeded",
    "Cold_Continuation_Succeeded",
}


def _run_embedded(program, states, *args):
    """The embedded controller's rows (u..., path, microseconds) for ``states``, one run."""
    text = "".join(" ".join(repr(float(v)) for v in x) + "\n" for x in states)
    out = subprocess.run([str(program), *args], input=text, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    return np.array([[float(v) for v in line.split()] for line in out.stdout.splitlines()])


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")
def test_the_embedded_controller_needs_libc_and_libm_only_and_gives_the_mpcs_input(cstr, tmp_path):
    """Compiled (-O0 for a fast test; benchmarks/embedded_time.py times -O2 on 100 states), it
    links nothing but libc and libm, and its input equals ParametricMPC.solve's within 1e-6:
    cold on 20 states of the box (after a reset: IPOPT from the cold guess) wherever it
    converges, which is on 17 of them at least, and warm along closed loops of the MPC."""
    mpc = ParametricMPC(cstr)
    d = export_embedded(mpc, None, tmp_path / "emb")
    proc = subprocess.run(embedded_compile_command(d, optimize="-O0"), capture_output=True)
    assert proc.returncode == 0, proc.stderr
    if shutil.which("ldd"):
        ldd = subprocess.run(["ldd", str(d / "controller")], capture_output=True, text=True)
        libs = [line.split()[0] for line in ldd.stdout.splitlines() if line.strip()]
        allowed = ("linux-vdso.so", "libc.so", "libm.so", "/lib64/ld-linux", "/lib/ld-linux")
        assert libs and all(lib.startswith(allowed) for lib in libs), libs
    states = _box_states(cstr, 20)
    rows = _run_embedded(d / "controller", states, "--cold")
    solved = 0
    for x, row in zip(states, rows):
        mpc.reset()
        sol = mpc.solve(x, sensitivities=False)
        if row[cstr.nu] == 0:  # the fallback: no plan yet, so the reference input
            np.testing.assert_allclose(row[: cstr.nu], cstr.clip_input(cstr.u_ref))
            continue
        assert sol.success
        np.testing.assert_allclose(row[: cstr.nu], sol.action, rtol=0, atol=1e-6)
        solved += 1
    assert solved >= 17
    mpc.reset()
    x, loop, actions = np.array([100.0, 0.15, 430.0]), [], []
    for _ in range(20):
        sol = mpc.solve(x, sensitivities=False)
        loop.append(x)
        actions.append(sol.action)
        x = cstr.plant_step(x, sol.action)
    rows = _run_embedded(d / "controller", loop)
    np.testing.assert_allclose(rows[:, : cstr.nu], np.array(actions), rtol=0, atol=1e-6)
    assert np.sum(rows[:, cstr.nu] == 1) >= 15  # the warm steps take the Newton path
    # a state written with commas is not read as the end of the input
    bad = subprocess.run([str(d / "controller")], input=b"100,0.15,430\n", capture_output=True)
    assert bad.returncode == 2 and b"a state is 3 numbers separated by spaces" in bad.stderr
    # from a hot start the closed loop takes every path but the cold one; a root that is a
    # saddle point is refused as the MPC refuses it (here at step 31, where both restart), so
    # the inputs agree until the MPC hands a step to IPOPT, which the controller does not have
    rng = np.random.default_rng(2025)
    x = [cstr.sample_initial_state(rng) for _ in range(4)][3]
    mpc.reset()
    loop, actions, paths = [], [], []
    while len(loop) < 60:
        sol = mpc.solve(x, sensitivities=False)
        if sol.status not in OWN_PATHS:  # IPOPT's
            break
        loop.append(x)
        actions.append(sol.action)
        paths.append(sol.status)
        x = cstr.plant_step(x, sol.action)
    rows = _run_embedded(d / "controller", loop)
    np.testing.assert_allclose(rows[:, : cstr.nu], np.array(actions), rtol=0, atol=1e-6)
    assert "Restart_Continuation_Succeeded" in paths and len(loop) >= 30
    restarted = [k for k, st in enumerate(paths) if st == "Restart_Continuation_Succeeded"]
    assert np.all(rows[restarted, cstr.nu] == 4)


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")
def test_the_command_line_writes_and_builds_the_embedded_controller(tmp_path):
    """``export --format embedded --compile`` on a tuner with one told trial (``lq``): the
    program it builds gives the deployed MPC's input."""
    from mpcmobo.experiment.tuner import Tuner

    tuner = Tuner({"name": "lq", "identify": False}, "bo", tmp_path / "t", episodes=2, steps=10)
    trial = tuner.ask()
    x, states, inputs = trial.x0, [trial.x0], []
    for k in range(trial.steps):
        u = np.clip(trial.policy(x) + trial.noise[k], tuner.system.u_lb, tuner.system.u_ub)
        x = tuner.system.plant_step(x, u)
        states.append(x)
        inputs.append(u)
    tuner.tell(trial, np.array(states), np.array(inputs))
    out = tmp_path / "emb"
    res = CliRunner().invoke(
        app, ["export", str(tmp_path / "t"), "--format", "embedded", "-o", str(out), "--compile"]
    )
    assert res.exit_code == 0 and "mpc_functions.c" in res.output, res.output
    theta = tuner.deployed
    mpc = ParametricMPC(get_system("lq"))
    x = np.array([0.8, -0.3])
    row = _run_embedded(out / "controller", [x], "--cold")[0]
    np.testing.assert_allclose(row[: mpc.nu], mpc.solve(x, theta, False).action, atol=1e-6)


def test_a_controller_casadi_cannot_save_or_generate_is_refused(tmp_path, monkeypatch):
    """Equations with a Python ``casadi.Callback`` run in mpcmobo but CasADi can neither load
    their saved function back nor generate C for them (its code says ``#error``): the export
    says so and leaves no file that looks usable."""
    from mpcmobo.mpc.export import ExportError, check_generated

    source, header = tmp_path / "controller.c", tmp_path / "controller.h"
    source.write_text(
        "int f(void) {\n  #error Code generation not supported for CallbackInternal\n}\n"
    )
    header.write_text("")
    with pytest.raises(ExportError, match="not supported for CallbackInternal.*casadi.Callback"):
        check_generated(source, [source, header])
    assert not source.exists() and not header.exists()
    (tmp_path / "t.c").write_text("int f;\n")
    check_generated(tmp_path / "t.c", [])  # generated code without an #error passes

    def unloadable(path):
        raise RuntimeError("FunctionInternal::deserialize: not found 'CallbackInternal'")

    monkeypatch.setattr(ca.Function, "load", staticmethod(unloadable))
    mpc = ParametricMPC(get_system("lq"), codegen=False)
    with pytest.raises(ExportError, match="cannot be saved as a CasADi function"):
        export_casadi(mpc, None, tmp_path / "m.casadi")
    assert not (tmp_path / "m.casadi").exists()
