"""``python -m mpcmobo``: the command line (as ``mpcmobo``)."""

from mpcmobo.cli import app

app(prog_name="mpcmobo")
