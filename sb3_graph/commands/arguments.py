"""Argument types and checks that several commands share (each error names its flag)."""

from __future__ import annotations

import argparse
import math
from typing import Any

from sb3_graph.commands import UserError


def json_object(text: str) -> dict[str, Any]:
    """``argparse`` type of ``--env-kwargs``: a JSON object.

    :raises argparse.ArgumentTypeError: invalid JSON, or JSON that is not an object
    """
    from sb3_graph.files.safe_values import UnsafeValueError, load_json

    try:
        value = load_json(text, "value", constants=False)
    except UnsafeValueError as error:
        raise argparse.ArgumentTypeError(str(error).removeprefix("value: ")) from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(
            f"""must be a JSON object such as '{{"config": {{"duration": 60}}}}', got {text!r}"""
        )
    return value


json_object.__name__ = "JSON object"  # argparse names the type in its messages


def finite_float(text: str) -> float:
    """``argparse`` type: a finite number (``inf`` and ``nan`` are refused)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


#: largest seed accepted (numpy's legacy seeding, SB3's ``set_random_seed`` and gymnasium take 32 bits)
MAX_SEED = 2**32 - 1


def seed_value(text: str) -> int:
    """``argparse`` type of ``--seed``: an integer in ``[0, MAX_SEED]``."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer in [0, {MAX_SEED}], got {text!r}") from None
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"expected an integer in [0, {MAX_SEED}], got {text!r}")
    return value


seed_value.__name__ = "seed"


def check_device(device: str, flag: str = "--device") -> str:
    """A torch device name that torch understands (``auto`` too).

    :raises UserError: naming the flag and the accepted forms
    """
    if device == "auto":
        return device
    import torch as th

    try:
        th.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise UserError(f"{flag}: {device!r} is not a torch device (auto, cpu, cuda, cuda:0, mps ...)") from None
    return device
