"""The config parser: dicts from YAML, JSON or a checkpoint's metadata into config dataclasses."""

import dataclasses
from dataclasses import dataclass, field

import pytest

from axispose_core.config import PRESET, ConfigError, config_from_dict, nest_moved_keys, yaml_mapping


@dataclass(frozen=True)
class Inner:
    size: int = 64


@dataclass(frozen=True)
class Outer:
    name: str
    inner: Inner = field(default_factory=Inner)
    scales: tuple[float, ...] = (1.0,)


@dataclass(frozen=True)
class NetA:
    """One of two network configs that can fill a slot, told apart by their `kind`."""

    kind: str = "a"
    width: int = 8


@dataclass(frozen=True)
class NetB:
    """The other: the same fields as NetA and one more, so that a dict without a kind fits both."""

    kind: str = "b"
    width: int = 8
    depth: int = 2


@dataclass(frozen=True)
class Slots:
    either: NetA | NetB | None = None
    only: NetA = field(default_factory=NetA)


def test_a_config_union_is_resolved_by_kind_never_by_the_first_class_that_fits():
    assert config_from_dict(Slots, {"either": {"kind": "b", "width": 4}}).either == NetB(width=4)
    assert config_from_dict(Slots, {"either": {"kind": "a", "width": 4}}).either == NetA(width=4)  # NetB would fit too
    with pytest.raises(ConfigError, match="'kind' must say which of"):
        config_from_dict(Slots, {"either": {"width": 4}})
    with pytest.raises(ConfigError, match="kind 'c' is not one of"):
        config_from_dict(Slots, {"either": {"kind": "c"}})
    with pytest.raises(ConfigError, match="kind 'b' is not one of"):  # a single-class slot checks the kind too
        config_from_dict(Slots, {"only": {"kind": "b", "width": 4}})
    assert config_from_dict(Slots, {"only": {"width": 4}}).only == NetA(width=4)  # written before kinds: the only class


def test_keys_that_moved_into_a_section_are_read_from_where_an_earlier_version_wrote_them():
    from axispose_core.train.agm import TrainConfig

    cfg = TrainConfig()
    now = dataclasses.asdict(cfg)
    # Before `optim` gathered the optimiser's fields (`seed` is also one of the stream's, which was written), and
    # before `agm.encoder_loss` gathered the encoder's loss weights.
    old = {k: v for k, v in now.items() if k != "optim"} | now["optim"]
    old["agm"] = {k: v for k, v in now["agm"].items() if k != "encoder_loss"} | now["agm"]["encoder_loss"]
    assert nest_moved_keys(TrainConfig, old) == now
    assert config_from_dict(TrainConfig, old) == cfg
    with pytest.raises(ConfigError, match=r"unknown key.*no_such_field"):
        config_from_dict(TrainConfig, old | {"no_such_field": 1})


def test_config_errors_name_the_key():
    with pytest.raises(ConfigError, match="missing key 'name'"):
        config_from_dict(Outer, {})
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['colour'\]"):
        config_from_dict(Outer, {"name": "x", "colour": 1})
    with pytest.raises(ConfigError, match=r"inner.*unknown key"):
        config_from_dict(Outer, {"name": "x", "inner": {"size": 3, "depth": 2}})


@dataclass(frozen=True)
class Look:
    light: Inner = field(default_factory=Inner)
    ambient: float = 0.5
    gamma: float = 1.0


@dataclass(frozen=True)
class Stream:
    """Two sections with the same non-default default: one marked a preset, one not."""

    look: Look = field(default_factory=lambda: Look(Inner(32), 0.3, 2.0), metadata=PRESET)
    plain: Look = field(default_factory=lambda: Look(Inner(32), 0.3, 2.0))


def test_a_partial_preset_section_changes_only_what_it_names():
    """A preset's section given in part keeps the preset's other values, nested ones too; an unmarked section given
    in part starts from its class's defaults, as the recipes that predate presets were resolved."""
    cfg = config_from_dict(Stream, {"look": {"ambient": 1.0}, "plain": {"ambient": 1.0}})
    assert cfg.look == Look(Inner(32), 1.0, 2.0)
    assert cfg.plain == Look(Inner(64), 1.0, 1.0)
    assert config_from_dict(Stream, {"look": {"light": {}}}).look == Look(Inner(32), 0.3, 2.0)
    assert config_from_dict(Stream, {}).look == Look(Inner(32), 0.3, 2.0)
    with pytest.raises(ConfigError, match="unknown key"):
        config_from_dict(Stream, {"look": {"ambiant": 1.0}})


def test_the_crop_streams_appearance_keeps_its_preset_when_a_recipe_changes_one_light_setting():
    from axispose_core.data.synth.config import STREAM_RANDOMIZATION, StreamConfig

    cfg = config_from_dict(StreamConfig, {"randomization": {"light": {"ambient": [0.15, 1.0]}}})
    light = dataclasses.replace(STREAM_RANDOMIZATION.light, ambient=(0.15, 1.0))
    assert cfg.randomization == dataclasses.replace(STREAM_RANDOMIZATION, light=light)


def test_a_yaml_mapping_is_read_inline_or_from_a_file_and_anything_else_refused(tmp_path):
    (tmp_path / "c.yaml").write_text("optim: {steps: 3}\n")
    assert yaml_mapping("{rounds: 2}") == {"rounds": 2} and yaml_mapping(str(tmp_path / "c.yaml")) == {"optim": {"steps": 3}}
    assert yaml_mapping("", empty_ok=True) == {}
    for text, message in (("", "expected a YAML mapping"), ("[1, 2]", "expected a YAML mapping"), ("{a: [", "not YAML")):
        with pytest.raises(ConfigError, match=message):
            yaml_mapping(text)
