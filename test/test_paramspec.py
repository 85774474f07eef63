"""One parameter definition: core dataclass fields -> validation, offline reading, ROS params."""
from __future__ import annotations

import re
from dataclasses import dataclass

import pytest

from maem_ros.core.association import PAPER_PIPELINE, AssociationParams, ExecutionParams
from maem_ros.core.paramspec import ParamError, Params, ParamSpec, param, param_specs
from maem_ros.core.triangulation.ransac import TriangulationParams
from maem_ros.params import load_node_params


@dataclass
class _Example(Params):
    gain: float = param(1.5, "m, a gain", minimum=0.0, exclusive_minimum=True, maximum=10.0)
    count: int = param(3, "a count", minimum=1)
    mode: str = param("a", "a mode", choices=("a", "b"))
    on: bool = param(True, "a switch")
    names: list = param([], "some names")


def test_specs_come_from_the_field_metadata() -> None:
    specs = {s.name: s for s in _Example.specs()}
    assert list(specs) == ["gain", "count", "mode", "on", "names"]
    g = specs["gain"]
    assert (g.default, g.description, g.minimum, g.maximum, g.exclusive_minimum) == (
        1.5, "m, a gain", 0.0, 10.0, True)
    assert g.ptype is float and specs["names"].ptype is list and specs["on"].ptype is bool
    assert g.constraints() == "> 0, <= 10"
    assert specs["mode"].help_line() == "mode (str, default 'a', one of a|b): a mode"


def test_construction_validates_and_normalises() -> None:
    e = _Example(gain=2, count=4.0, names=("x", "y"))
    assert (e.gain, type(e.gain), e.count, type(e.count), e.names) == (2.0, float, 4, int,
                                                                       ["x", "y"])
    assert _Example().names == [] and _Example().names is not _Example().names


@pytest.mark.parametrize("name,value,problem", [
    ("gain", 0.0, "must be > 0, <= 10"), ("gain", 11, "must be > 0"), ("gain", "1", "a number"),
    ("gain", True, "a number"), ("gain", float("inf"), "finite"), ("count", 2.5, "an integer"),
    ("count", 0, ">= 1"), ("mode", "c", "one of ['a', 'b']"), ("on", 1, "true/false"),
    ("names", "x", "list of strings"),
])
def test_bad_values_name_the_parameter(name: str, value, problem: str) -> None:
    with pytest.raises(ParamError, match=f"^{name}: .*{re.escape(problem)}") as info:
        _Example.from_mapping({name: value})
    assert info.value.name == name


def test_from_mapping_ignores_other_keys_and_reads_shipped_params() -> None:
    assert _Example.from_mapping({"gain": 3.0, "rig": "x"}).gain == 3.0
    p = TriangulationParams.from_mapping(load_node_params("sportcenter.yaml", "triangulation"))
    assert p.tau_kps == 20.0 and p.min_views == 2


def test_param_specs_joins_classes_and_rejects_a_name_twice() -> None:
    names = [s.name for s in param_specs(AssociationParams, TriangulationParams)]
    tri = [s.name for s in TriangulationParams.specs()]
    assert names[:2] == ["tau_det", "tau_reproj_bbox"] and tri[:2] == ["tau_kps", "min_views"]
    assert names == [s.name for s in AssociationParams.specs()] + tri
    with pytest.raises(TypeError, match="'tau_det' defined twice"):
        param_specs(AssociationParams, AssociationParams)


#: the performance settings, apart from the method's thresholds since the pair gates were sealed
EXECUTION = ["backend", "epipolar_precision", "early_exit", "screen_stride", "screen_margin",
             "screen_coarse_stride", "screen_coarse_margin"]


def test_method_and_execution_params_are_apart_and_read_from_the_old_flat_keys() -> None:
    """AssociationParams holds the method's thresholds, its ExecutionParams how it runs; a
    params file that names every parameter flat (as shipped, as before the split) loads the
    same values into both, and an ``execution`` sub-mapping is read too."""
    assert [s.name for s in ExecutionParams.specs()] == EXECUTION
    assert not {s.name for s in AssociationParams.specs()} & set(EXECUTION)
    assert len(AssociationParams.specs()) + len(EXECUTION) == 23
    shipped = load_node_params("sportcenter.yaml", "association")
    assert {"screen_stride", "screen_coarse_margin", "tau_mesh"} <= set(shipped)
    old = {**shipped, "backend": "numpy", "early_exit": False, "screen_stride": 4,
           "epipolar_precision": "float64", "tau_mesh": 7.5}
    p = AssociationParams.from_mapping(old)
    assert p.tau_mesh == 7.5 and p.execution == ExecutionParams(
        backend="numpy", early_exit=False, screen_stride=4, epipolar_precision="float64",
        screen_margin=shipped["screen_margin"], screen_coarse_stride=shipped["screen_coarse_stride"],
        screen_coarse_margin=shipped["screen_coarse_margin"])
    known = {s.name for s in AssociationParams.specs()} | set(EXECUTION)
    assert p.as_mapping() == {**{s.name: s.default for s in AssociationParams.specs()},
                              **ExecutionParams().as_mapping(),
                              **{k: v for k, v in old.items() if k in known}}
    assert AssociationParams.from_mapping(p.as_mapping()) == p
    nested = AssociationParams.from_mapping({"tau_mesh": 7.5, "execution": {"screen_stride": 4}})
    assert nested.execution.screen_stride == 4 and nested.tau_mesh == 7.5
    paper = p.replaced(PAPER_PIPELINE)
    assert paper.clustering == "paper" and paper.execution.screen_levels() == []
    assert paper.execution.backend == "numpy" and p.clustering == "consistent"
    with pytest.raises(ParamError, match="^screen_stride: must be >= 1"):
        AssociationParams.from_mapping({"screen_stride": 0})
    with pytest.raises(ValueError, match="^execution: expected a mapping"):
        AssociationParams.from_mapping({"execution": 3})


def test_the_association_node_declares_both_groups_flat() -> None:
    from maem_ros.ros import association_node
    names = [s.name for s in association_node.PARAMS]
    assert set(EXECUTION) <= set(names) and {"tau_mesh", "tau_cost", "temporal"} <= set(names)
    assert len(names) == len(set(names))


def test_every_node_parameter_has_a_description() -> None:
    from maem_ros.ros import association_node, camera_node, frontend_node, triangulation_node
    for mod in (association_node, camera_node, frontend_node, triangulation_node):
        for spec in mod.PARAMS:
            assert isinstance(spec, ParamSpec) and spec.description, (mod.__name__, spec.name)
            assert spec.check(spec.default) == spec.default, (mod.__name__, spec.name)


@pytest.mark.ros
def test_a_new_core_field_is_a_validated_read_only_ros_parameter() -> None:
    """What an added field gets in a node: declaration with descriptor, ints for doubles, and a
    one-line ConfigError naming it."""
    import rclpy
    from rclpy.parameter import Parameter

    from maem_ros.ros.params import ConfigError, declare_params

    def declare(overrides: list[Parameter]):
        ctx = rclpy.Context()
        rclpy.init(context=ctx)
        node = rclpy.create_node("paramspec_test", context=ctx, parameter_overrides=overrides)
        try:
            return declare_params(node, _Example.specs()), node.describe_parameter("gain")
        finally:
            node.destroy_node()
            rclpy.try_shutdown(context=ctx)

    values, desc = declare([Parameter("gain", value=4), Parameter("names", value=["a"])])
    assert values == {"gain": 4.0, "count": 3, "mode": "a", "on": True, "names": ["a"]}
    assert type(values["gain"]) is float and _Example.from_mapping(values).gain == 4.0
    assert desc.description == "m, a gain" and desc.read_only
    assert desc.additional_constraints == "> 0, <= 10"
    with pytest.raises(ConfigError, match=r"^parameter 'mode': expected one of \['a', 'b'\]"):
        declare([Parameter("mode", value="z")])
    with pytest.raises(ConfigError, match=r"^parameter 'gain': expected a number"):
        declare([Parameter("gain", value="big")])
