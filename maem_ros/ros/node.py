"""The base class of the processing nodes: parameters, diagnostics, configuration errors and
the process around the node (signals, spinning, shutdown), so a node file holds only its own
logic (params -> wire -> core -> publish).

A node subclasses :class:`MaemNode` with ``NAME`` (node name and ``ros2 run`` executable),
``PARAMS`` (its ParamSpecs, from the one definition in core.paramspec / maem_ros.params) and
optionally ``HEAP_PREFAULT_MB``; its module's ``main`` is ``return TheNode.main(args)``.
``self.p`` holds the validated parameter values, :meth:`start_diagnostics` creates ``self.diag``
(/diagnostics: inputs, ``dropped/<reason>`` counters, stage timings), ``with
self.config_errors():`` turns a core ValueError into a one-line ConfigError (exit code 2).
Signals and shutdown belong to run_node (ros/process.py): SIGINT/SIGTERM end the spin between
callbacks and the node is destroyed either way.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any, ClassVar

from rclpy.node import Node
from rclpy.task import Future

from maem_ros.core.paramspec import ParamSpec
from maem_ros.ros.diagnostics import Diagnostics
from maem_ros.ros.params import ConfigError, declare_params, load_rig_param
from maem_ros.ros.process import run_node


class MaemNode(Node):
    """A node whose parameters are declared read-only from ``PARAMS`` at construction."""

    #: node name (also the executable's name in --help)
    NAME: ClassVar[str] = ""
    #: every parameter the node declares at construction
    PARAMS: ClassVar[Sequence[ParamSpec]] = ()
    #: parameters --help lists (default PARAMS; more when the node declares some itself)
    HELP_PARAMS: ClassVar[Sequence[ParamSpec] | None] = None
    #: MiB of heap grown and touched before the node starts (process.keep_freed_memory)
    HEAP_PREFAULT_MB: ClassVar[int] = 0

    def __init__(self, **kwargs: Any):
        super().__init__(self.NAME, **kwargs)
        self.p: dict[str, Any] = declare_params(self, self.PARAMS)

    def start_diagnostics(self, hardware_id: str = "maem_ros") -> Diagnostics:
        """Create ``self.diag``, published every ``diagnostics_period`` s (1 s for a node
        without that parameter)."""
        self.diag = Diagnostics(self, self.p.get("diagnostics_period", 1.0), hardware_id)
        return self.diag

    def load_rig(self, name: str = "rig") -> Any:
        """The Rig the parameter ``name`` names (ConfigError if it names none)."""
        return load_rig_param(self.p[name], name)

    @staticmethod
    @contextmanager
    def config_errors(prefix: str = "") -> Iterator[None]:
        """A ValueError raised inside (a core class refusing a value) becomes a ConfigError:
        the node does not start and the process exits with one line and code 2."""
        try:
            yield
        except ConfigError:
            raise
        except ValueError as e:
            raise ConfigError(f"{prefix}{e}") from None

    @classmethod
    def main(cls, args: list[str] | None = None, until: Callable[[Node], Future] | None = None) -> int:
        """Run the node in this process (run_node): --help prints the module docstring's
        summary and the parameters; exit code 0 at SIGINT/SIGTERM, 2 on a bad parameter, or
        with ``until`` the result of the future it returns for the node."""
        return run_node(
            cls,
            args,
            cls.NAME,
            until=until,
            specs=cls.PARAMS if cls.HELP_PARAMS is None else cls.HELP_PARAMS,
            doc=sys.modules[cls.__module__].__doc__,
            heap_prefault_mb=cls.HEAP_PREFAULT_MB,
        )
