"""String options as enums, resolved from names (the theseus pattern); resource limits read from the
environment (:func:`env_limit`); the compute device of the commands' ``--device`` (:func:`resolve_device`)."""

from __future__ import annotations

import math
import os
import re
from enum import Enum
from typing import TYPE_CHECKING, TypeVar

from torchgarment.errors import InputError

if TYPE_CHECKING:
    import torch

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


DEVICE_CHOICES = ("cpu", "cuda")
"""The values of the commands' ``--device`` option."""


def resolve_device(name: object) -> torch.device:
    """The torch device for a ``--device`` value: ``cpu``, ``cuda`` or ``cuda:N``.

    Raises:
        InputError: an unknown name, CUDA asked for on a machine without it, or a GPU index it lacks.
    """
    import torch

    text = str(name).strip().lower()
    expected = f"--device {name}: expected one of {', '.join(DEVICE_CHOICES)} (or cuda:N)"
    try:
        device = torch.device(text)
    except RuntimeError:
        raise InputError(expected) from None
    if device.type not in DEVICE_CHOICES:
        raise InputError(expected)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise InputError(f"--device {name}: CUDA is not available on this machine (use --device cpu)")
        count = torch.cuda.device_count()
        if device.index is not None and device.index >= count:
            raise InputError(f"--device {name}: this machine has {count} CUDA device(s)")
    return device


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
