"""String options as enums, resolved from names (the theseus pattern); resource limits read from the
environment (:func:`env_limit`)."""

from __future__ import annotations

import math
import os
import re
from enum import Enum
from typing import TypeVar

from torchgarment.errors import InputError

_E = TypeVar("_E", bound="OptionEnum")


class OptionEnum(str, Enum):
    """Base of the string-valued option enums: ``resolve`` turns a member or a name into a member.

    Names are matched case-insensitively after stripping blanks; a subclass may accept synonyms by overriding
    :meth:`aliases`. Unknown names raise :class:`InputError` listing the valid ones.
    """

    @classmethod
    def aliases(cls) -> dict[str, str]:
        """Extra accepted names, mapped to member values (none by default)."""
        return {}

    @classmethod
    def resolve(cls: type[_E], value: object) -> _E:
        """The member for ``value`` (a member, its value or an alias); :class:`InputError` otherwise."""
        if isinstance(value, cls):
            return value
        name = str(value).strip().lower()
        name = cls.aliases().get(name, name)
        try:
            return cls(name)
        except ValueError:
            label = re.sub(r"(?<=[a-z])(?=[A-Z])|(?<=[A-Z])(?=[A-Z][a-z])", " ", cls.__name__).lower()
            known = ", ".join(m.value for m in cls)
            synonyms = "".join(f", {a} (= {v})" for a, v in cls.aliases().items())
            raise InputError(f"unknown {label} {value!r}; expected one of: {known}{synonyms}") from None


def env_limit(name: str, default: float, minimum: float) -> float:
    """A resource limit: the environment variable ``name`` when set, else ``default``.

    Args:
        name: the variable (e.g. ``"TORCHGARMENT_MAX_VERTICES"``).
        default: the documented default.
        minimum: the smallest accepted value.

    Raises:
        InputError: the variable is set to something that is not a finite number >= ``minimum``.
    """
    raw = os.environ.get(name)
    if raw is None:
        return default
    try:
        value = float(raw)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value >= minimum):
        raise InputError(f"{name} must be a number >= {minimum:g}, got {raw!r}")
    return value
