"""How the fixture was made, with mpcmobo at commit 9ff9153 (0.1.0): python make_fixture.py OUT,
then OUT/partial (without its rebuilt records) is ``run/`` and OUT/full's records are ``expected_*``.

It runs with that version only: mpcmobo 1.0 refuses to resume ``run/`` and reads its records
(tests/test_old_checkpoints.py)."""

import sys
from pathlib import Path

from mpcmobo.experiment import load_settings, run_study


def main():
    root = Path(sys.argv[1])
    kw = dict(
        system={"name": "lq"},
        learners=["mpc-rl", "mobo"],
        episodes=8,
        steps=10,
        seeds=[0],
        workers=1,
        learner_options={"mobo": {"n_init": 3}},
        evaluation={"n_starts": 2, "eval_every": 2},
        records={"trajectory_every": 3},
    )
    s = load_settings(**kw)
    run_study(s, root / "full")
    run_study(s, root / "partial", max_episodes_this_call=4)


if __name__ == "__main__":
    main()
