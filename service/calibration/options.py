"""The options every calibration job shares, light enough for ``vtolpose calibrate --help``."""

from __future__ import annotations

import argparse


def add_output_options(p: argparse.ArgumentParser, default_stem: str, figure: bool = True) -> None:
    """``--out`` (the block) and, for jobs with a figure, ``--plot`` / ``--no-plot``."""
    p.add_argument("--out", default=f"{default_stem}.yaml", metavar="FILE.yaml",
                   help=f"configuration block to write (default {default_stem}.yaml)")
    if figure:
        p.add_argument("--plot", metavar="FILE.png", help="figure to write (default: --out with .png)")
        p.add_argument("--no-plot", action="store_true", help="no figure (matplotlib not needed)")
