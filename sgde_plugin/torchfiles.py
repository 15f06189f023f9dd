"""torch model files: `torch.export` archives (.pt2) read with one-line errors, and TorchScript files."""

from __future__ import annotations

import logging
import warnings
import zipfile
from pathlib import Path
from typing import Any

import torch
from torch import nn

from .errors import InputError


def load_exported_program(path: str | Path, device: str = "cpu") -> Any:
    """The `torch.export.ExportedProgram` of a `torch.export.save` archive, moved to `device`; InputError otherwise."""
    path = Path(path)
    if not zipfile.is_zipfile(path):
        raise InputError(path, None, "not a torch.export archive (not a zip file)")
    log = logging.getLogger("torch.export")
    level = log.level
    log.setLevel(logging.ERROR)  # a damaged archive is logged with its traceback before it raises
    try:
        program = torch.export.load(str(path))
    except Exception as exc:  # noqa: BLE001 - any unreadable archive is bad input
        raise InputError(path, None, f"not a readable torch.export archive ({type(exc).__name__})") from None
    finally:
        log.setLevel(level)
    if device != "cpu":
        program = torch.export.passes.move_to_device_pass(program, device)
    return program


def load_torchscript(path: str | Path) -> Any:
    """A TorchScript file (`torch.jit.save`) on the CPU; torch's errors pass through for the caller to name."""
    with warnings.catch_warnings():  # torch >= 2.10 deprecates TorchScript on every load; .pt2 is the successor
        warnings.simplefilter("ignore", FutureWarning)
        return torch.jit.load(str(path), map_location="cpu")


class ExportedModule(nn.Module):
    """An exported program as a module; its train / eval mode was fixed when it was exported."""

    def __init__(self, program: Any):
        super().__init__()
        self.program = program.module()

    def train(self, mode: bool = True) -> ExportedModule:
        """No-op: an exported program cannot switch between training and inference."""
        return self

    def forward(self, *inputs: torch.Tensor) -> Any:
        """The program on `inputs`; inputs outside the shapes it was exported for are bad input."""
        try:
            return self.program(*inputs)
        except (AssertionError, RuntimeError) as exc:
            if "guard" not in str(exc).lower():
                raise
            shapes = ", ".join(str(tuple(x.shape)) for x in inputs)
            raise InputError(None, "exported program", f"refuses inputs of shape {shapes} "
                             f"({str(exc).splitlines()[0]}); re-export it with wider dynamic_shapes") from None


__all__ = ["ExportedModule", "load_exported_program", "load_torchscript"]
