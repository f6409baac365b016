"""``tracegs view``: a trained run in the browser, at any time, observed or predicted.

``camera.py`` (the browser's camera as a tracegs camera), ``scene.py`` (the Gaussians at a time under
TRACE's physics or f_defo alone, a rendered frame, the segments, the dataset's cameras), ``server.py``
(the viser page: time slider, play, toggles, frusta; :func:`serve`).

``serve`` is imported on first use, so that the CLI reads this package without torch or viser.
"""

from importlib import import_module

_WHERE = {"serve": "server", "Viewer": "server", "ViewerConfig": "server"}
__all__ = sorted(_WHERE)


def __getattr__(name: str):
    if name in _WHERE:
        return getattr(import_module(f".{_WHERE[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
