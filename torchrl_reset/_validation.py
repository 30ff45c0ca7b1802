"""Argument checks shared by the components: errors that name the argument, the bound and the value."""
from __future__ import annotations

from typing import Any


def is_int_at_least(value: Any, minimum: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= minimum


def check_int(name: str, value: Any, minimum: int = 1) -> int:
    """Returns ``value`` if it is an integer >= ``minimum`` (bools refused), else raises ValueError."""
    if not is_int_at_least(value, minimum):
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}.")
    return value
