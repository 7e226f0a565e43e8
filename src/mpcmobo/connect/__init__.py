"""Trials on a live plant over OPC UA: ``mpcmobo connect`` and :func:`run_plant`.

- :mod:`mpcmobo.connect.nodes`: the node map (``nodes.toml``) and the client's security;
- :mod:`mpcmobo.connect.client`: the OPC UA client, one batched read and write per period;
- :mod:`mpcmobo.connect.runner`: one trial, period by period, on a deadline;
- :mod:`mpcmobo.connect.session`: ask, run, tell, and what the tool does on each fault.

``asyncua`` is the optional extra ``opcua`` (``pip install "mpcmobo[opcua]"``); importing
this package does not need it.
"""

from mpcmobo.connect.nodes import ConnectError, NodeMap, load_nodes
from mpcmobo.connect.session import Outcome, PlantInterrupted, run_plant

__all__ = ["ConnectError", "NodeMap", "Outcome", "PlantInterrupted", "load_nodes", "run_plant"]
