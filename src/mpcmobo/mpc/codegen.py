"""Generated C code of CasADi functions, compiled once per machine and problem, cached on disk.

``compiled_library(functions)`` writes the C code of ``functions`` (and everything they call)
into one file, compiles it into a shared library and returns its path. The library's name is a
hash of the functions' serialization, the CasADi version, the compiler and its flags, so a
second MPC of the same problem, in this or any later process, loads the library instead of
compiling again; a changed problem gets a new file. Files are written under a temporary name
and renamed into place (an atomic ``os.replace``), so worker processes that build the same
MPC at the same time never load a half-written library: the last rename wins, and all of them
wrote the same code.

The cache directory: ``$MPCMOBO_CACHE_DIR``, else ``$XDG_CACHE_HOME/mpcmobo``, else
``~/.cache/mpcmobo``; ``codegen-*.so`` files there can be deleted at any time.
"""

from __future__ import annotations

import hashlib
import os
import platform
import shlex
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import casadi as ca

#: compiler flags of the generated code (part of the cache key)
DEFAULT_FLAGS = ("-O1", "-fPIC", "-shared")


def cache_directory() -> Path:
    """Where compiled libraries are kept (created on first use)."""
    env = os.environ.get("MPCMOBO_CACHE_DIR")
    if env:
        return Path(env).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg).expanduser() if xdg else Path.home() / ".cache"
    return base / "mpcmobo"


def compiler_command() -> list[str]:
    """The C compiler: ``$CC`` (may carry flags), else ``cc``."""
    return shlex.split(os.environ.get("CC", "cc"))


def compiler_available() -> bool:
    """Whether the C compiler (:func:`compiler_command`) is on the path."""
    cc = compiler_command()
    return bool(cc) and shutil.which(cc[0]) is not None


def require_compiler() -> list[str]:
    """The C compiler's command (:func:`compiler_command`), or a ``RuntimeError`` saying what
    to do if it is not on the path."""
    cc = compiler_command()
    if not compiler_available():
        raise RuntimeError(
            f"codegen needs a C compiler, and {cc[0] if cc else '$CC'!r} was not found: set $CC, "
            "or turn codegen off ([mpc] codegen = false; ParametricMPC(..., codegen=False))"
        )
    return cc


def library_key(functions: list[ca.Function], flags: tuple[str, ...] = DEFAULT_FLAGS) -> str:
    """Hash of what the compiled library depends on: the functions, CasADi, compiler, flags."""
    h = hashlib.sha256()
    for part in (ca.CasadiMeta.version(), platform.machine(), " ".join(compiler_command()), *flags):
        h.update(part.encode())
        h.update(b"\0")
    for f in functions:
        h.update(f.name().encode())
        h.update(f.serialize().encode())
    return h.hexdigest()[:32]


def compiled_library(
    functions: list[ca.Function],
    *,
    directory: str | os.PathLike | None = None,
    flags: tuple[str, ...] = DEFAULT_FLAGS,
    info: dict | None = None,
) -> Path:
    """Path of a shared library with the compiled C code of ``functions`` (cached on disk).

    ``info``, if given, receives ``{"path", "cached" (bool), "seconds" (compile time or 0)}``.
    Raises ``RuntimeError`` naming the compiler and its error output when compiling fails.
    """
    directory = Path(directory).expanduser() if directory is not None else cache_directory()
    key = library_key(functions, flags)
    path = directory / f"codegen-{key}.so"
    if info is not None:
        info.update(path=str(path), cached=True, seconds=0.0)
    if path.exists():
        return path
    directory.mkdir(parents=True, exist_ok=True)
    cc = require_compiler()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(dir=directory, prefix=".build-") as tmp:
        name = f"codegen_{key}"
        gen = ca.CodeGenerator(f"{name}.c", {"with_header": False})
        for f in functions:
            gen.add(f)
        gen.generate(tmp + os.sep)
        src = Path(tmp) / f"{name}.c"
        out = Path(tmp) / f"{name}.so"
        cmd = [*cc, *flags, str(src), "-o", str(out), "-lm"]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            raise RuntimeError(
                f"compiling the MPC's generated code failed ({shlex.join(cmd)}):\n"
                f"{proc.stderr.strip()[-2000:]}"
            )
        os.replace(out, path)  # atomic: a concurrent builder never sees a partial file
    if info is not None:
        info.update(cached=False, seconds=time.perf_counter() - t0)
    return path
