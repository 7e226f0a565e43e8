"""Results on disk that survive a crash: atomic files, job checkpoints, Parquet records.

Layout of a study directory ``DIR``::

    config.toml                      every setting used (written first)
    reference.pkl                    J*, J_eval(theta0), evaluation episodes of theta0 / perfect MPC
    jobs/<learner>-s<seed>/checkpoint.pkl
                                     LearningRun state + all rows + stored trajectories of one job,
                                     rewritten atomically after every episode
    jobs/<learner>-s<seed>/checkpoint.prev.pkl
                                     the generation before (read if the latest cannot be)
    run.log                          library warnings and worker output (``logs.py``)
    .stop                            only while an interrupted study stops its workers
    running.json                     only while the study runs: its process (``rundir.py``)
    episodes.parquet                 per-episode rows of all jobs (rebuilt from the checkpoints)
    trajectories.parquet             states/inputs, long format (rebuilt from the checkpoints)
    summary.json                     per-learner results
    figures/                         ``mpcmobo plot DIR``

Every file is written to a temporary file in the same directory, flushed, fsync'ed and moved
over the target with ``os.replace``, so a reader sees the old or the new file, never a torn one.
"""

from __future__ import annotations

import io
import json
import math
import os
import pickle
import secrets
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mpcmobo.experiment.records import ROW_FIELDS

if TYPE_CHECKING:
    import pandas as pd

# the checkpoint format, raised with every change of a learner's state: 3 since mpcmobo 1.2
# (the declared learner contract: identify-first's inner learner, MPC-RL's evidence); 2 was
# written by 1.0 and 1.1, 1 by 0.1.0 (SCHEMA_WRITERS)
CHECKPOINT_SCHEMA = 3
SCHEMA_WRITERS = {1: "mpcmobo 0.1.0", 2: "mpcmobo 1.0 or 1.1"}
EPISODE_COLUMNS = list(ROW_FIELDS)
WALL_TIME_COLUMNS = ("mpc_time_s", "learner_time_s", "eval_time_s")


# ---------------------------------------------------------------------- atomic files
def _create_temp(directory: Path, name: str) -> tuple[int, Path]:
    """A new, empty temporary file next to ``directory/name``, open for writing.

    Created with mode 0o666 so that the kernel applies the process umask, as for any file the
    user creates (``tempfile.mkstemp`` would force 0o600); the umask is never read or changed.
    """
    tmp = directory / f".{name}.{secrets.token_hex(6)}.tmp"
    return os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666), tmp


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # pragma: no cover - e.g. platforms without directory fds
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover
        pass
    finally:
        os.close(fd)


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (temp file in the same dir, fsync, os.replace)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = _create_temp(path.parent, path.name)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    _fsync_dir(path.parent)
    return path


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def _json_safe(obj: Any) -> Any:
    """NaN/inf -> None, numpy -> Python, so the JSON is standard."""
    if isinstance(obj, dict):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _json_safe(obj.tolist())
    if isinstance(obj, np.bool_ | bool):
        return bool(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, float | np.floating):
        f = float(obj)
        return f if math.isfinite(f) else None
    return obj


def json_safe(obj: Any) -> Any:
    """``obj`` as standard JSON data: NaN and inf as None, NumPy values as Python's."""
    return _json_safe(obj)


def write_json(path: str | Path, obj: Any) -> Path:
    """Write ``obj`` as standard JSON (NaN and inf as null) atomically."""
    text = json.dumps(_json_safe(obj), indent=2, allow_nan=False)
    return atomic_write_text(path, text + "\n")


def read_json(path: str | Path) -> Any:
    """The JSON file at ``path``."""
    return json.loads(Path(path).read_text(encoding="utf-8"))


def write_toml(path: str | Path, obj: dict) -> Path:
    """Write ``obj`` as TOML atomically."""
    import tomli_w

    return atomic_write_text(path, tomli_w.dumps(obj))


def write_pickle(path: str | Path, obj: Any) -> Path:
    """Write ``obj`` as a pickle atomically."""
    return atomic_write_bytes(path, pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL))


def read_pickle(path: str | Path) -> Any:
    """The pickled object at ``path``."""
    with Path(path).open("rb") as fh:
        return pickle.load(fh)


def write_parquet(path: str | Path, df: pd.DataFrame) -> Path:
    """Write ``df`` as Parquet (pyarrow, no index) atomically."""
    buf = io.BytesIO()
    df.to_parquet(buf, index=False, engine="pyarrow")
    return atomic_write_bytes(path, buf.getvalue())


# ---------------------------------------------------------------------- study layout
def job_name(learner: str, seed: int) -> str:
    """The job's name and directory name, ``<learner>-s<seed>``."""
    return f"{learner}-s{int(seed)}"


def checkpoint_path(out_dir: str | Path, learner: str, seed: int) -> Path:
    """The job's checkpoint file, ``DIR/jobs/<job>/checkpoint.pkl``."""
    return Path(out_dir) / "jobs" / job_name(learner, seed) / "checkpoint.pkl"


def previous_checkpoint_path(out_dir: str | Path, learner: str, seed: int) -> Path:
    """The job's previous checkpoint, ``DIR/jobs/<job>/checkpoint.prev.pkl``."""
    return checkpoint_path(out_dir, learner, seed).with_name("checkpoint.prev.pkl")


def save_checkpoint(out_dir: str | Path, learner: str, seed: int, ckpt: dict) -> Path:
    """Write the job's checkpoint atomically; the one it replaces becomes
    ``checkpoint.prev.pkl`` (a hard link made before the replacement, so that the latest
    checkpoint exists at every moment)."""
    ckpt = dict(ckpt, schema=CHECKPOINT_SCHEMA, learner=learner, seed=int(seed))
    path = checkpoint_path(out_dir, learner, seed)
    data = pickle.dumps(ckpt, protocol=pickle.HIGHEST_PROTOCOL)
    if path.exists():
        prev = previous_checkpoint_path(out_dir, learner, seed)
        tmp = path.with_name(f".{prev.name}.{secrets.token_hex(6)}.tmp")
        try:
            os.link(path, tmp)
            os.replace(tmp, prev)
        except OSError:  # no hard links here: a copy
            atomic_write_bytes(prev, path.read_bytes())
    return atomic_write_bytes(path, data)


def load_checkpoint(out_dir: str | Path, learner: str, seed: int) -> dict | None:
    """The job's checkpoint as a dictionary (None if there is none)."""
    path = checkpoint_path(out_dir, learner, seed)
    if not path.exists():
        return None
    ckpt = read_pickle(path)
    if checkpoint_schema(ckpt) != CHECKPOINT_SCHEMA:
        raise ValueError(f"{path}: checkpoint schema {checkpoint_schema(ckpt)} is not supported")
    return ckpt


def checkpoint_schema(ckpt: dict) -> int | None:
    """The schema of a checkpoint's dictionary: its ``schema`` key (1.0 and later) or 1 for
    mpcmobo 0.1.0's (a ``version`` key of 1); None when it is neither."""
    if "schema" in ckpt:
        return int(ckpt["schema"])
    return 1 if ckpt.get("version") == 1 else None


def load_checkpoints(out_dir: str | Path, jobs: Iterable[tuple[str, int]]) -> list[dict]:
    """The checkpoints of ``jobs`` that exist."""
    out = []
    for learner, seed in jobs:
        ckpt = load_checkpoint(out_dir, learner, seed)
        if ckpt is not None:
            out.append(ckpt)
    return out


def episodes_frame(checkpoints: list[dict]) -> pd.DataFrame:
    """All rows of the checkpoints, ordered by learner (as given), seed and episode."""
    import pandas as pd

    rows = [r for c in checkpoints for r in c["rows"]]
    if not rows:
        return pd.DataFrame({c: pd.Series(dtype=object) for c in EPISODE_COLUMNS})
    df = pd.DataFrame(rows)
    cols = [c for c in EPISODE_COLUMNS if c in df.columns]
    cols += [c for c in df.columns if c not in cols]
    df = df[cols]
    order = {c["learner"]: i for i, c in reversed(list(enumerate(checkpoints)))}
    df["_o"] = df["learner"].map(order)
    df = df.sort_values(["_o", "seed", "episode"], kind="stable").drop(columns="_o")
    return df.reset_index(drop=True)


def trajectory_rows(
    learner: str,
    seed: int,
    phase: str,
    episode: int,
    start: int,
    x: np.ndarray,
    u: np.ndarray,
    state_names: Iterable[str],
    input_names: Iterable[str],
    dt: float,
) -> pd.DataFrame:
    """Long format: one row per time index k of one trajectory (u is NaN at k = T)."""
    import pandas as pd

    x, u = np.asarray(x, float), np.asarray(u, float)
    T1 = x.shape[0]
    d: dict[str, Any] = {
        "learner": [learner] * T1,
        "seed": np.full(T1, int(seed)),
        "phase": [phase] * T1,
        "episode": np.full(T1, int(episode)),
        "start": np.full(T1, int(start)),
        "k": np.arange(T1),
        "t": np.arange(T1) * float(dt),
    }
    for i, n in enumerate(state_names):
        d[f"x_{n}"] = x[:, i]
    upad = np.full((T1, u.shape[1]), np.nan)
    upad[: u.shape[0]] = u
    for i, n in enumerate(input_names):
        d[f"u_{n}"] = upad[:, i]
    return pd.DataFrame(d)


def trajectories_frame(
    reference: dict | None,
    checkpoints: list[dict],
    state_names: Sequence[str],
    input_names: Sequence[str],
    dt: float,
) -> pd.DataFrame:
    """The study-level (learner "", seed -1) and per-job stored trajectories, long format."""
    import pandas as pd

    parts = []
    items: list[tuple[str, int, dict]] = []
    if reference is not None:
        items += [("", -1, t) for t in reference.get("trajectories", [])]
    for c in checkpoints:
        items += [(c["learner"], c["seed"], t) for t in c.get("trajectories", [])]
    for learner, seed, t in items:
        parts.append(
            trajectory_rows(
                learner,
                seed,
                t["phase"],
                t["episode"],
                t["start"],
                t["x"],
                t["u"],
                state_names,
                input_names,
                dt,
            )
        )
    if not parts:
        return pd.DataFrame(columns=["learner", "seed", "phase", "episode", "start", "k", "t"])
    return pd.concat(parts, ignore_index=True)


def read_episodes(out_dir: str | Path) -> pd.DataFrame:
    """``DIR/episodes.parquet``, one row per episode."""
    import pandas as pd

    return pd.read_parquet(Path(out_dir) / "episodes.parquet")


def read_trajectories(out_dir: str | Path) -> pd.DataFrame:
    """``DIR/trajectories.parquet``, the stored states and inputs."""
    import pandas as pd

    return pd.read_parquet(Path(out_dir) / "trajectories.parquet")
