"""Benchmarks that a user runs to reproduce docs/RESULTS.md (``tracegs bench ...``): the rasteriser's
speed (``raster``), the fields' cost (``fields``), and quality tables (``methods``, ``ablations``). Each
writes a results record into docs/results/ only when asked (``--json``); ``tracegs results`` makes
docs/RESULTS.md from the records.
"""

from .fields import run_field_bench
from .raster import run_raster_bench
from .variants import ABLATIONS, METHODS, OPTIONS, PAPER, run_variant_table, scene_folder, validation_cut

__all__ = [
    "ABLATIONS",
    "METHODS",
    "OPTIONS",
    "PAPER",
    "run_field_bench",
    "run_raster_bench",
    "run_variant_table",
    "scene_folder",
    "validation_cut",
]
