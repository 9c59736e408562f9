"""Reading ``torch.save`` files (model weights) with one-line errors; writing goes through :mod:`lidarmap.io.atomic`."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from lidarmap.errors import InputError


def read_torch_file(path: str | Path | None, default: Path, what: str, train_script: str) -> tuple[Path, Any]:
    """Load ``path`` (``default``, the shipped file, when None) onto the CPU with ``weights_only`` (no pickled code).

    ``what`` names the file in errors ("model file"); a missing shipped file also names the script that makes it.
    """
    import torch

    path = Path(path) if path is not None else default
    if not path.exists():
        hint = f" (the shipped file is missing: run {train_script})" if path == default else ""
        raise InputError(f"{what} not found{hint}", path)
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - torch.load raises many kinds (struct.error, UnpicklingError, ...)
        raise InputError(f"not a readable model file ({' '.join(str(exc).split())[:160]})", path) from None
    return path, data
