"""Shipped weights: the segmentation models and the learned upsampler (``scripts/`` reproduces them)."""

from pathlib import Path

#: Folder of the shipped weight files.
WEIGHTS_DIR = Path(__file__).resolve().parent
