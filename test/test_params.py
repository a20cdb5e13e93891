"""The node's parameter table: one spec per NodeSettings field, and the change check the node registers."""

from dataclasses import fields

from rclpy.parameter import Parameter

from axispose_core.tracking.poser import PoserSettings
from axispose_ros.params import AT_START, SPECS, NodeSettings, check_change


def test_every_setting_is_declared_once_and_start_only_ones_are_refused_later():
    names = [s.name for s in SPECS]
    assert len(names) == len(set(names)) and set(names) == {f.name for f in fields(NodeSettings)} - {"object_scales"}
    assert AT_START == {"checkpoint", "device", "precision", "objects", "use_rectified", "sync_slop", "num_threads",
                        "warmup_boxes", "batch_boxes", "latency_budget"}  # fmt: skip
    assert not check_change([Parameter("num_threads", value=4)]).successful
    assert check_change([Parameter("ddim_steps", value=8), Parameter("object_scales.ape", value=0.06)]).successful
    assert not check_change([Parameter("object_scales.ape", value=10.5)]).successful
    assert not check_change([Parameter("object_scales.ape", value=1)]).successful  # an integer is no length


def test_an_objects_own_scale_wins_over_the_common_one():
    values = {s.name: s.default for s in SPECS if not isinstance(s.default, Parameter.Type)}
    settings = NodeSettings(**values | {"object_scale": 0.1}, objects=(), object_scales={"ape": 0.06, "can": 0.0})
    assert settings.scales({1: "ape", 5: "can"}) == {1: 0.06, 5: 0.1}
    assert NodeSettings(**values, objects=(), object_scales={"ape": 0.0}).scales({1: "ape"}) == {}


def test_the_posers_settings_are_the_nodes_parameters_of_those_names():
    """`PoserSettings` (axispose_core: no ROS) holds the parameters the frame poser reads, with the node's defaults;
    `NodeSettings.poser` copies them and resolves λ_O for the published objects."""
    values = {s.name: s.default for s in SPECS if not isinstance(s.default, Parameter.Type)}
    read = {f.name for f in fields(PoserSettings)} - {"scales"}
    assert read <= set(values) and {n: getattr(PoserSettings(), n) for n in read} == {n: values[n] for n in read}
    node = NodeSettings(**values | {"mode": "video", "redetect_period": 9}, objects=(), object_scales={"ape": 0.06})
    assert node.poser({1: "ape", 5: "can"}) == PoserSettings(mode="video", redetect_period=9, scales={1: 0.06})
