"""tracegs: TRACE (translation-rotation dynamics for 3D Gaussian splatting) as a library and CLI."""

__version__ = "0.1.0"
