"""How much of f3 is the episode's start (issue 11, item 4): paper f3 against ``same_states``.

MPC-RL does not use f3, so two MPC-RL runs that differ only in ``[critic] f3`` run the same
thetas from the same cycled starts; their f3 columns are the two definitions on the same
episodes. The table gives, per definition, the share of f3's variance explained by the start
(one-way ANOVA over the cycled start index, on the values and on their ranks) and how often
f3 is non-zero.

    mpcmobo run --config paper.toml --learner mpc-rl --episodes 60 --seeds 0 --out runs/f3/paper
    mpcmobo run --config same.toml  --learner mpc-rl --episodes 60 --seeds 0 --out runs/f3/same
    python benchmarks/f3_start_share.py runs/f3/paper runs/f3/same

(``paper.toml``: ``[critic] f3 = "paper"``; ``same.toml``: ``f3 = "same_states"``.)
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.stats import rankdata, spearmanr


def start_share(values: np.ndarray, groups: np.ndarray) -> float:
    """R^2 of a one-way ANOVA: between-group sum of squares over the total."""
    total = np.sum((values - values.mean()) ** 2)
    if total == 0:
        return float("nan")
    between = sum(
        np.sum(groups == g) * (values[groups == g].mean() - values.mean()) ** 2
        for g in np.unique(groups)
    )
    return float(between / total)


def main(paper: Path, same: Path) -> None:
    a = pd.read_parquet(paper / "episodes.parquet").sort_values("episode")
    b = pd.read_parquet(same / "episodes.parquet").sort_values("episode")
    ta, tb = np.stack(a["theta"].to_numpy()), np.stack(b["theta"].to_numpy())
    if ta.shape != tb.shape or not np.array_equal(ta, tb):
        raise SystemExit("the two runs did not run the same thetas: not a paired comparison")
    x0 = np.stack(a["x0"].to_numpy())
    _, start = np.unique(np.round(x0, 12), axis=0, return_inverse=True)
    start = start.reshape(-1)
    keep = a["episode"].to_numpy() >= 1  # f3 of the first episode is 0 by definition
    print(f"episodes {int(keep.sum())} (from 1), {len(np.unique(start))} cycled starts")
    print("| f3 | start share of the variance (values) | (ranks) | non-zero | median |")
    print("|---|---|---|---|---|")
    for name, d in (("paper", a), ("same_states", b)):
        f3 = d["f3"].to_numpy()[keep]
        g = start[keep]
        print(
            f"| {name} | {start_share(f3, g):.2f} | {start_share(rankdata(f3), g):.2f} "
            f"| {np.mean(f3 > 0):.2f} | {np.median(f3):.3g} |"
        )
    rho = spearmanr(a["f3"].to_numpy()[keep], b["f3"].to_numpy()[keep]).statistic
    print(f"\nSpearman correlation of the two definitions on the same episodes: {rho:.2f}")
    print(f"chance level of the start share (6 groups, no effect): ~{5 / (keep.sum() - 1):.2f}")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
