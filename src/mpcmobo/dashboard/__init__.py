"""A live, read-only page of run and tuner directories (``mpcmobo dashboard``).

:func:`make_server` serves the page (:mod:`~mpcmobo.dashboard.server`); the page polls the
runs' data, which :mod:`~mpcmobo.dashboard.payload` builds from the files that
:mod:`~mpcmobo.dashboard.runs` reads through a cache that never raises
(:mod:`~mpcmobo.dashboard.files`). The plotting library, uPlot (MIT), ships with the package
(``static/vendor/``); no asset is fetched from the network.
"""

from mpcmobo.dashboard.server import Dashboard, make_server

__all__ = ["Dashboard", "make_server"]
