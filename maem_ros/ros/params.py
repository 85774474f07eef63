"""ROS parameters of a node, declared from the one definition (core.paramspec ParamSpec):
read-only, typed descriptors, one-line ConfigError on a bad value."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from rcl_interfaces.msg import ParameterDescriptor, ParameterType
from rclpy.exceptions import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    ParameterException,
)
from rclpy.node import Node
from rclpy.parameter import Parameter

from maem_ros.core.paramspec import ParamError, Params, ParamSpec, param

#: exit code of a node whose parameters are invalid
EXIT_CONFIG_ERROR = 2


class ConfigError(ValueError):
    """A parameter value the node cannot start with (reported as one line, exit code 2)."""


_PTYPE = {
    bool: ParameterType.PARAMETER_BOOL,
    int: ParameterType.PARAMETER_INTEGER,
    float: ParameterType.PARAMETER_DOUBLE,
    str: ParameterType.PARAMETER_STRING,
    list: ParameterType.PARAMETER_STRING_ARRAY,
}


@dataclass
class NodeParams(Params):
    """Parameters every processing node has (node-only parameter classes subclass this)."""

    diagnostics_period: float = param(
        1.0, "s, /diagnostics publish period (steady clock)", minimum=0.0, exclusive_minimum=True
    )


def declare_params(node: Node, specs: Sequence[ParamSpec]) -> dict[str, Any]:
    """Declare read-only parameters with descriptors; return {name: validated value}.

    Parameters are dynamically typed for rclpy and type-checked by ParamSpec.check, so an
    integer given for a double parameter (``tau_mesh: 8``) is accepted and converted. Any bad
    value raises ConfigError with one line naming the parameter.
    """
    out: dict[str, Any] = {}
    for spec in specs:
        desc = ParameterDescriptor(
            name=spec.name,
            type=_PTYPE[spec.ptype],
            description=spec.description,
            additional_constraints=spec.constraints(),
            read_only=True,
        )
        try:
            if spec.ptype is list:  # rclpy cannot infer a type from [] (string arrays only)
                value = node.declare_parameter(spec.name, Parameter.Type.STRING_ARRAY, desc).value
                value = list(spec.default) if value is None else value
            else:
                desc.dynamic_typing = True
                value = node.declare_parameter(spec.name, spec.default, desc).value
        except InvalidParameterTypeException as e:
            raise ConfigError(
                f"parameter '{spec.name}': expected {spec.ptype.__name__} ({_short(e)})"
            ) from None
        except (InvalidParameterValueException, ParameterException) as e:
            raise ConfigError(f"parameter '{spec.name}': {_short(e)}") from None
        try:
            out[spec.name] = spec.check(value)
        except ParamError as e:
            raise ConfigError(f"parameter '{e.name}': {e.problem}") from None
    return out


def _short(e: Exception) -> str:
    return " ".join(str(e).split())[:200]


def default_camera_name(node: Node) -> str:
    """The last component of the node's namespace ('' at the root namespace)."""
    return node.get_namespace().rstrip("/").rsplit("/", 1)[-1]


def load_rig_param(value: str, name: str = "rig"):
    """The Rig named by a ``rig`` parameter (file, folder or shipped name); ConfigError if not."""
    from maem_ros.core.geometry.camera import Rig
    from maem_ros.params import resolve_rig_path

    if not value:
        raise ConfigError(f"parameter '{name}': required (rig YAML, camera-JSON folder or shipped rig name)")
    try:
        return Rig.load(resolve_rig_path(value))
    except (ValueError, OSError) as e:
        raise ConfigError(f"parameter '{name}': {e}") from None
