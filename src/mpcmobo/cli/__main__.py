"""``python -m mpcmobo.cli``: the command line."""

from mpcmobo.cli import app

app()
