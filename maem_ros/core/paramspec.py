"""One definition per parameter: dataclass fields declared with :func:`param`.

A parameter dataclass (core: AssociationParams, TriangulationParams; node-only: each node's
``*NodeParams``) subclasses :class:`Params` and declares every field with ``param()``::

    @dataclass
    class AssociationParams(Params):
        tau_mesh: float = param(8.0, "px, dense-mesh epipolar gate", minimum=0.0,
                                exclusive_minimum=True)

That one line is all a new parameter needs: construction validates it (ValueError starting with
the field name), ``from_mapping`` reads it from a params-file section (offline tools), and the
ROS nodes declare it as a read-only ROS parameter with its description and constraints and list
it in ``--help`` (ros/cli.py). The type of the default is the parameter type (bool, int,
float, str; a list default is a string array). Pure Python: no rclpy here.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import MISSING, dataclass, field, fields
from typing import Any

import numpy as np

#: dataclass field metadata key holding a field's ParamSpec keyword arguments
PARAM_METADATA = "maem_param"


class ParamError(ValueError):
    """A bad parameter value: ``str(e)`` is ``"<name>: <problem>"``."""

    def __init__(self, name: str, problem: str):
        super().__init__(f"{name}: {problem}")
        self.name, self.problem = name, problem


@dataclass(frozen=True)
class ParamSpec:
    """One parameter: name, default (its type is the parameter type), description, checks.

    ``minimum``/``maximum`` bound numbers (inclusive unless ``exclusive_minimum``), ``choices``
    restricts strings. ``list`` defaults are string arrays.
    """

    name: str
    default: Any
    description: str
    minimum: float | None = None
    maximum: float | None = None
    exclusive_minimum: bool = False
    choices: tuple[str, ...] | None = None

    @property
    def ptype(self) -> type:
        """bool, int, float, str or list (string array)."""
        return list if isinstance(self.default, (list, tuple)) else type(self.default)

    def constraints(self) -> str:
        """Human-readable bounds/choices ('' if none), e.g. '> 0, <= 1000'."""
        parts = []
        if self.minimum is not None:
            parts.append(f"{'>' if self.exclusive_minimum else '>='} {self.minimum:g}")
        if self.maximum is not None:
            parts.append(f"<= {self.maximum:g}")
        if self.choices:
            parts.append("one of " + "|".join(repr(c) if c == "" else c for c in self.choices))
        return ", ".join(parts)

    def help_line(self) -> str:
        """``name (type, default D[, constraints]): description`` for --help."""
        extra = f", {self.constraints()}" if self.constraints() else ""
        return f"{self.name} ({self.ptype.__name__}, default {self.default!r}{extra}): {self.description}"

    def check(self, value: Any) -> Any:
        """The validated value in the parameter's type (ints accepted for floats, integral
        floats for ints); ParamError naming the parameter otherwise."""
        t = self.ptype
        if t is list:
            if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple, np.ndarray)):
                raise ParamError(self.name, f"expected a list of strings, got {value!r}")
            return [str(v) for v in value]
        if t is bool:
            if not isinstance(value, (bool, np.bool_)):
                raise ParamError(self.name, f"expected true/false, got {value!r}")
            value = bool(value)
        elif t in (int, float):
            value = self._number(value, t)
        elif not isinstance(value, t):
            raise ParamError(self.name, f"expected {t.__name__}, got {value!r}")
        if self.choices is not None and value not in self.choices:
            raise ParamError(self.name, f"expected one of {list(self.choices)}, got {value!r}")
        return value

    def _number(self, value: Any, t: type) -> int | float:
        if isinstance(value, (bool, np.bool_, str)) or not isinstance(value, (int, float, np.number)):
            raise ParamError(self.name, f"expected {'an integer' if t is int else 'a number'}, got {value!r}")
        if not math.isfinite(value):
            raise ParamError(self.name, f"must be finite, got {value!r}")
        if t is int:
            if int(value) != value:
                raise ParamError(self.name, f"expected an integer, got {value!r}")
            value = int(value)
        else:
            value = float(value)
        low = self.minimum is not None and (
            value <= self.minimum if self.exclusive_minimum else value < self.minimum
        )
        if low or (self.maximum is not None and value > self.maximum):
            raise ParamError(self.name, f"must be {self.constraints()}, got {value!r}")
        return value


def param(
    default: Any,
    description: str,
    *,
    minimum: float | None = None,
    maximum: float | None = None,
    exclusive_minimum: bool = False,
    choices: Sequence[str] | None = None,
) -> Any:
    """A dataclass field that is a parameter (see module docstring); list defaults are copied."""
    meta = {
        PARAM_METADATA: dict(
            description=description,
            minimum=minimum,
            maximum=maximum,
            exclusive_minimum=exclusive_minimum,
            choices=None if choices is None else tuple(choices),
        )
    }
    if isinstance(default, (list, tuple)):
        items = list(default)
        return field(default_factory=lambda: list(items), metadata=meta)
    return field(default=default, metadata=meta)


class Params:
    """Base of parameter dataclasses: validates every ``param()`` field after construction.

    Subclasses needing cross-field checks override ``__post_init__`` and call
    ``super().__post_init__()`` first.
    """

    def __post_init__(self) -> None:
        for spec in self.specs():
            setattr(self, spec.name, spec.check(getattr(self, spec.name)))

    @classmethod
    def specs(cls) -> tuple[ParamSpec, ...]:
        """The ParamSpec of every ``param()`` field, in declaration order."""
        out = []
        for f in fields(cls):  # type: ignore[arg-type]
            if PARAM_METADATA not in f.metadata:
                continue
            default = f.default if f.default is not MISSING else f.default_factory()  # type: ignore[operator]  # set when no default
            out.append(ParamSpec(f.name, default, **f.metadata[PARAM_METADATA]))
        return tuple(out)

    @classmethod
    def from_mapping(cls, d: Mapping[str, Any]):
        """An instance from the known keys of a params dict (others are ignored); validated."""
        return cls(**{s.name: d[s.name] for s in cls.specs() if s.name in d})

    def as_mapping(self) -> dict[str, Any]:
        """Every parameter's value by name (what :meth:`from_mapping` reads back)."""
        return {spec.name: getattr(self, spec.name) for spec in self.specs()}


def param_specs(*classes: type[Params]) -> tuple[ParamSpec, ...]:
    """The specs of several parameter classes (one node's parameters); a name twice is a bug."""
    out: dict[str, ParamSpec] = {}
    for cls in classes:
        for spec in cls.specs():
            if spec.name in out:
                raise TypeError(f"parameter {spec.name!r} defined twice ({cls.__name__})")
            out[spec.name] = spec
    return tuple(out.values())
