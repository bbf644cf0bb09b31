"""``python -m server.cli``: the ``xneck`` command line."""

from server.cli import main

main()
