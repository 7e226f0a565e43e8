"""mpcmobo: tune an MPC from closed-loop data (MPC-based RL, BO, multi-objective BO).

Importing the package registers the paper's CSTR plant with gymnasium as ``mpcmobo/CSTR-v0``
(and the test bed ``mpcmobo/LQ-v0``), lazily: the entry points are strings, nothing heavy is
imported here.
"""

import gymnasium as _gymnasium

for _id, _name, _steps in (("mpcmobo/CSTR-v0", "cstr", 60), ("mpcmobo/LQ-v0", "lq", 30)):
    if _id not in _gymnasium.registry:
        _gymnasium.register(
            id=_id,
            entry_point="mpcmobo.systems.plant:SystemPlant",
            kwargs={"system": _name},
            max_episode_steps=_steps,
        )
