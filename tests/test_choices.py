"""The names a user chooses from are written once (thgs.choices), and every registry that gives
them a meaning, and every command that offers them, holds exactly those names."""

from __future__ import annotations

import typing

import pytest

import thgs.cli
from thgs.choices import DEVICES, FIELD_PRESETS, SCENE_PRESETS, SELECTION_MODES
from thgs.device import resolve_device
from thgs.errors import InputError
from thgs.pipeline import PRESETS
from thgs.synthetic import PRESETS as SCENES


def test_the_registries_hold_the_offered_names():
    assert tuple(PRESETS) == FIELD_PRESETS
    assert tuple(SCENES) == SCENE_PRESETS
    assert resolve_device("auto").type in ("cpu", "cuda", "mps")
    assert resolve_device("cpu").type == "cpu"
    for name in DEVICES[2:]:  # known names: present, or refused as absent (never as unknown)
        try:
            assert resolve_device(name).type == name
        except InputError as error:
            assert "unknown" not in str(error)
    with pytest.raises(InputError, match="unknown"):
        resolve_device("tpu")
    from thgs.query import QueryConfig
    from thgs.viewer.state import QUERY_MODES

    assert tuple(QUERY_MODES) == SELECTION_MODES
    for mode in SELECTION_MODES:
        assert QueryConfig(mode=mode).check().mode == mode
    with pytest.raises(InputError, match="must be auto, paper, level or threshold"):
        QueryConfig(mode="best").check()


def offered(command: str, option: str) -> tuple:
    hint = typing.get_type_hints(thgs.cli.COMMANDS[command], include_extras=True)[option]
    choices = [arg for arg in typing.get_args(hint) if arg is not type(None)]
    return typing.get_args(choices[0]) if len(choices) == 1 else typing.get_args(hint)


@pytest.mark.parametrize(
    ("command", "option", "names"),
    [
        ("build", "preset", FIELD_PRESETS),
        ("suite", "preset", FIELD_PRESETS),
        ("synth", "preset", SCENE_PRESETS),
        ("demo", "preset", SCENE_PRESETS),
        *[(c, "device", DEVICES) for c in ("build", "query", "pick", "eval", "view", "suite")],
        ("bench", "device", DEVICES),
        *[(c, "mode", SELECTION_MODES) for c in ("query", "export", "catalog", "view")],
    ],
)
def test_every_command_offers_exactly_those_names(command, option, names):
    assert offered(command, option) == names
