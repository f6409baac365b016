"""`tracegs bench WHAT` (``cli.commands.Bench``): the benchmark its flags name, run and recorded."""

from __future__ import annotations

from . import ABLATIONS, METHODS, OPTIONS, run_field_bench, run_raster_bench, run_variant_table


def bench_command(a):
    """The records of the benchmark that ``a`` (the flags of `tracegs bench`) names; each goes to
    ``a.json`` when given."""
    if a.what == "raster":
        records = run_raster_bench(json_path=a.json, device=a.device, isas=a.isa)
    elif a.what == "fields":
        records = run_field_bench(json_path=a.json)
    else:
        table = METHODS if a.what == "methods" else ABLATIONS
        known = table if a.what == "methods" else ABLATIONS | OPTIONS
        unknown = set(a.variants) - set(known)
        if unknown:
            raise ValueError(f"--variants: unknown {sorted(unknown)}; choose from {list(known)}")
        variants = {k: v for k, v in known.items() if k in a.variants} if a.variants else table
        overrides = {} if a.device == "auto" else {"device": a.device}
        if a.dynamic_iterations is not None:
            overrides["dynamic_iterations"] = a.dynamic_iterations
        if a.seed is not None:
            overrides["seed"] = a.seed
        records = run_variant_table(
            a.what,
            variants,
            a.out,
            a.scenes,
            a.preset,
            a.resolution,
            overrides,
            train=not a.report_only,
            validation=a.validation,
            json_path=a.json,
            cluster=a.cluster,
            cpus_per_task=a.cpus_per_task,
        )
    return records
