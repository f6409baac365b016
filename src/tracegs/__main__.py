"""``python -m tracegs``: the same as the ``tracegs`` command."""

from .cli import main

main()
