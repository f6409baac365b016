"""``tracegs export``: a trained run's Gaussians at any time, the predicted future included, as files
that splat viewers and editors open.

One time writes one file (``RUN/export/gaussians_t<T>.ply`` by default); ``--times a:b:step`` writes a
numbered sequence ``NAME_0000.ply, NAME_0001.ply, ...`` (SuperSplat plays such a sequence on its
timeline) and ``NAME.json``: the times, the files, the end of the training span and which frames are
predicted. Formats: the 3DGS PLY (``ply.py``), the web viewers' ``.splat`` (``splat.py``), or both. With
``labels`` the Gaussians carry their segment's colour (``RUN/segments.pt`` of ``tracegs segment``).

N: Gaussians, K: SH coefficients per channel.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import torch
from tqdm.auto import tqdm

from ..extrapolate import check_time
from ..models.gaussians import rgb_to_sh0
from ..run import RunError, load_run, load_tensors
from ..utils import atomic_write_text
from .palette import colours
from .ply import write_gaussians
from .splat import write_splat

FORMATS = {"ply": (".ply",), "splat": (".splat",), "both": (".ply", ".splat")}
"""The ``--format`` values and the files each writes per time."""
MAX_FRAMES = 10_000
"""Most frames one ``--times`` sequence may hold."""
SEGMENTS = "segments.pt"
"""The labels ``tracegs segment`` stores in the run folder."""
_WRITERS = {".ply": write_gaussians, ".splat": write_splat}


def parse_times(spec: str, max_frames: int = MAX_FRAMES) -> list[float]:
    """The times ``a, a + step, ...`` of ``a:b:step`` up to ``b``, ``b`` included when it lands on the
    grid (to round-off: ``0:1.5:0.25`` is 7 times); ValueError naming ``--times`` for a bad spec. The
    run's own limit on the times (``extrapolate.check_time``) is checked once the run is read."""
    parts = str(spec).split(":")
    try:
        a, b, step = (float(x) for x in parts)
    except ValueError:
        raise ValueError(f"--times {spec!r}: expected START:STOP:STEP, e.g. 0:1.5:0.25") from None
    a, b = check_time(a, math.inf, "--times start"), check_time(b, math.inf, "--times stop")
    if not math.isfinite(step) or step <= 0:
        raise ValueError(f"--times {spec!r}: the step must be a finite number > 0")
    if b < a:
        raise ValueError(f"--times {spec!r}: the stop {b:g} is before the start {a:g}")
    ratio = (b - a) / step
    count = math.floor(ratio + 1e-9 * max(1.0, ratio)) + 1
    if count > max_frames:
        raise ValueError(f"--times {spec!r}: {count} frames, more than the {max_frames} a sequence may hold")
    return [round(a + i * step, 12) for i in range(count)]


def load_labels(run: Path, count: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(labels [N] long, palette [segments, 3]) of ``RUN/segments.pt``; RunError naming the file when
    there is none or when its labels are not one per Gaussian of the run (``count``)."""
    path = Path(run) / SEGMENTS
    if not path.is_file():
        raise RunError(f"{path}: no segmentation to colour by; make it with `tracegs segment --run {run}`")
    stored = load_tensors(path)
    try:
        labels = torch.as_tensor(stored["labels"]).long().reshape(-1)
        k, has_static = int(stored["k"]), bool(stored["has_static"])
    except (KeyError, TypeError, ValueError) as err:
        raise RunError(f"{path}: not the labels `tracegs segment` writes ({err})") from None
    if len(labels) != count:
        raise RunError(
            f"{path}: {len(labels)} labels for the run's {count} Gaussians (segmented before the run "
            f"changed?); segment again with `tracegs segment --run {run}`"
        )
    if len(labels) and not 0 <= int(labels.min()) <= int(labels.max()) < k:
        raise RunError(f"{path}: labels outside 0 .. {k - 1}")
    return labels, torch.as_tensor(colours(k, has_static), dtype=torch.float32)


def with_label_colours(
    params: dict[str, torch.Tensor], labels: torch.Tensor, palette: torch.Tensor
) -> dict[str, torch.Tensor]:
    """``params`` with each Gaussian's colour its segment's (``palette[labels]``) and view-independent:
    ``sh0`` the DC coefficients of that colour, ``shN`` zero (the same K, so the layout stays)."""
    dev = params["sh0"].device
    rgb = palette.to(dev)[labels.to(dev)]
    return params | {"sh0": rgb_to_sh0(rgb)[:, None, :], "shN": torch.zeros_like(params["shN"])}


def write_frame(params: dict[str, torch.Tensor], base: Path, fmt: str) -> list[Path]:
    """The files of one time: ``base`` followed by each suffix of ``FORMATS[fmt]``."""
    return [_WRITERS[suffix](params, base.with_name(base.name + suffix)) for suffix in FORMATS[fmt]]


def _base(path: Path) -> Path:
    """``path`` without a ``.ply`` / ``.splat`` suffix (``--ply out.ply --format both`` writes
    ``out.ply`` and ``out.splat``)."""
    return path.with_suffix("") if path.suffix.lower() in _WRITERS else path


def export_run(
    run: str | Path,
    time: float | None = None,
    times: str | None = None,
    ply: str | Path | None = None,
    out: str | Path | None = None,
    fmt: str = "ply",
    labels: bool = False,
    device: str = "auto",
    progress: bool = True,
) -> dict:
    """Export the Gaussians of ``run`` at one ``time`` (to ``ply``, default
    ``RUN/export/gaussians_t<T>.ply``; the ``.splat`` beside it) or at the ``times`` of ``a:b:step``
    (into ``out``, default ``RUN/export/sequence``, files named after ``ply``'s stem, default
    ``frame``) in ``fmt`` ("ply", "splat" or "both"); ``labels``: in their segment's colours. Returns
    the report (files, times, which are predicted, Gaussians) that the CLI prints."""
    if fmt not in FORMATS:
        raise ValueError(f"--format {fmt!r}: expected one of {', '.join(FORMATS)}")
    if (time is None) == (times is None):
        raise ValueError(
            "give --time T or --times START:STOP:STEP"
            + (", not both" if times else " (or --mjcf FILE / --urdf DIR for simulators)")
        )
    sequence = parse_times(times) if times is not None else [check_time(float(time), math.inf)]
    run = Path(run)
    predictor = load_run(run, device).predictor
    count = int(predictor.model.gaussians["means"].shape[0])
    colour = load_labels(run, count) if labels else None
    t_max = predictor.t_max
    predictor.check_time(sequence[-1], "--time" if times is None else "--times stop")

    def params_at(t: float) -> dict[str, torch.Tensor]:
        params = predictor.parameters_at(t)
        return params if colour is None else with_label_colours(params, *colour)

    report = {"run": str(run), "format": fmt, "labels": labels, "gaussians": count, "t_max": t_max}
    if times is None:
        t = sequence[0]
        files = write_frame(params_at(t), _base(Path(ply or run / "export" / f"gaussians_t{t:.3f}")), fmt)
        return report | {"times": [t], "predicted": [t > t_max], "files": [str(f) for f in files]}
    folder = Path(out) if out is not None else run / "export" / "sequence"
    name = _base(Path(ply)).name if ply is not None else "frame"
    written = []
    for i, t in enumerate(tqdm(sequence, desc="export", unit="frame", disable=not progress)):
        written.append(write_frame(params_at(t), folder / f"{name}_{i:04d}", fmt))
    index = {
        "times": sequence,
        "predicted": [t > t_max for t in sequence],
        "t_max": t_max,
        "files": {suffix[1:]: [frame[j].name for frame in written] for j, suffix in enumerate(FORMATS[fmt])},
        "gaussians": count,
        "labels": labels,
    }
    index_file = atomic_write_text(folder / f"{name}.json", json.dumps(index, indent=2))
    return report | {
        "times": sequence,
        "predicted": index["predicted"],
        "files": [str(f) for frame in written for f in frame],
        "index": str(index_file),
    }
