"""A field's build config as data: FieldConfig.from_json inverts to_json for every setting,
--set and --config reach every setting, a field rebuilds from its own record to the same bytes,
its scene path is stored relative to it, and eval renders with the raster settings it was lifted
with."""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import shutil
import typing

import numpy as np
import pytest

from test_cli import run
from thgs.errors import InputError
from thgs.features import FeatureConfig
from thgs.field import load_field
from thgs.field_scene import open_field_scene
from thgs.graph import PartitionConfig
from thgs.guidance import guidance_folder, guidance_space
from thgs.hierarchy import MergeConfig
from thgs.pipeline import (
    PRESETS,
    FieldConfig,
    chosen_field_config,
    lifted_raster,
    read_field_config,
    recorded_config,
)
from thgs.render import RasterConfig
from thgs.text import LANGSPLAT_SPACE


def leaves(config, prefix=""):
    """(dotted name, value, type) of every setting of a config dataclass."""
    hints = typing.get_type_hints(type(config))
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        if dataclasses.is_dataclass(value):
            yield from leaves(value, f"{prefix}{field.name}.")
        else:
            yield f"{prefix}{field.name}", value, hints[field.name]


def changed(value, kind):
    """A different valid value of the same type."""
    if typing.get_origin(kind) is typing.Literal:
        return next(choice for choice in typing.get_args(kind) if choice != value)
    if isinstance(value, bool):
        return not value
    if isinstance(value, int):
        return value - 1 if value > 1 else value + 1
    if isinstance(value, float):
        return value * 0.5 if 0 < value <= 1 else value + 0.125 if np.isfinite(value) else 2.5
    if isinstance(value, tuple):
        return tuple(v * 0.5 for v in value)
    raise AssertionError(f"no change for {value!r}")


@pytest.mark.parametrize("preset", sorted(PRESETS))
@pytest.mark.parametrize("reference", [False, True])
def test_from_json_inverts_to_json_for_the_presets(preset, reference):
    config = PRESETS[preset]()
    config = config.as_reference() if reference else config
    document = json.loads(json.dumps(config.to_json()))
    assert FieldConfig.from_json(document) == config
    assert FieldConfig.from_json(document).to_json() == document


def test_every_setting_round_trips_and_is_reachable_by_set():
    base = FieldConfig()
    names = []
    for name, value, kind in leaves(base):
        new = changed(value, kind)
        text = json.dumps(list(new) if isinstance(new, tuple) else new)
        config = base.with_settings([f"{name}={text}"])
        got = dict((n, v) for n, v, _ in leaves(config))
        assert got[name] == new, name
        assert {n: v for n, v in got.items() if n != name} == {
            n: v for n, v, _ in leaves(base) if n != name
        }
        if name.split(".")[-1] not in ("backend", "precision"):
            assert FieldConfig.from_json(config.to_json()) == config, name
        names.append(name)
    assert len(names) == 69  # every setting of every stage (update when one is added)


def test_set_takes_plain_text_for_choices():
    config = FieldConfig().with_settings(["superpoints.lift.raster.backend=torch"])
    assert config.superpoints.lift.raster.backend == "torch"


@pytest.mark.parametrize(
    ("assignment", "message"),
    [
        ("merge.rounds", "expected KEY=VALUE"),
        ("merge.round=3", "unknown setting 'merge.round'"),
        ("merges.rounds=3", "'merges' is not a stage"),
        ("merge.rounds=true", "--set.merge.rounds: must be an integer, got True"),
        ("merge.rounds=2.5", "must be an integer, got 2.5"),
        ("merge.thresholds=[0.5, 0.4]", "must hold 3 values, got 2"),
        ("features.mode=median", "must be one of ['shares', 'centres'], got 'median'"),
        ("repeats.enabled=1", "must be true or false, got 1"),
        ("superpoints.graph.k=1000000000000", "k: must be from 1 to 1,000 neighbours"),
        ("superpoints.lift.code_dim=100000000", "code_dim: must be from 2 to 1,024"),
        ("superpoints.lift.raster.tile_size=100000", "tile_size from 1 to 256"),
        ("superpoints.partition.regularization=1e30", "regularization must be from 0 to 100"),
        ("superpoints.partition.cp_it_max=1000000000", "cp_it_max must be from 1 to 1,000"),
        ("superpoints.partition.split_alternatives=100000", "split_alternatives must be from 2"),
        ("merge.neighbors=1000000000", "neighbors: must be from 2 to 1,000"),
        ("repeats.neighbors=1000000000", "neighbors: must be from 2 to 1,000"),
        ("features.median_steps=1000000000", "median_steps must be an integer from 0 to 1,000"),
    ],
)
def test_bad_settings_name_the_key(assignment, message):
    with pytest.raises(InputError, match=message.replace("[", r"\[").replace("]", r"\]")):
        FieldConfig().with_settings([assignment])


def test_from_json_refuses_unknown_keys_and_non_objects():
    document = FieldConfig().to_json()
    document["merge"]["speed"] = 1
    with pytest.raises(InputError, match=r"cfg\.merge: unknown setting 'speed'"):
        FieldConfig.from_json(document, "cfg")
    with pytest.raises(InputError, match="must be a JSON object, got list"):
        FieldConfig.from_json([], "cfg")


def test_a_missing_setting_takes_the_default():
    document = FieldConfig().to_json()
    del document["merge"]["rounds"]
    assert FieldConfig.from_json(document) == FieldConfig()


def test_a_config_file_names_what_it_leaves_to_the_defaults(tmp_path, caplog):
    document = FieldConfig().to_json()
    del document["merge"], document["superpoints"]["partition"]["block_size"]
    path = tmp_path / "partial.json"
    path.write_text(json.dumps(document))
    with caplog.at_level(logging.WARNING, logger="thgs.pipeline"):
        assert read_field_config(path) == FieldConfig()
    assert (
        f"{path} does not set superpoints.partition.block_size, merge: thgs's defaults are used"
        in caplog.text
    )


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[" * 100_000 + "]" * 100_000, "nested too deeply to read"),
        ('{"merge": {"rounds": ' + "9" * 5000 + "}}", "Exceeds the limit"),
    ],
)
def test_config_files_json_cannot_hold_are_named(tmp_path, text, message):
    path = tmp_path / "config.json"
    path.write_text(text)
    with pytest.raises(InputError, match=rf"{path}: not valid JSON \(.*{message}"):
        read_field_config(path)


def test_out_of_memory_is_one_line_not_a_traceback(small_dataset, tmp_path, capsys, monkeypatch):
    def too_much(*args, **kwargs):
        raise MemoryError("Unable to allocate 99.1 GiB")

    monkeypatch.setattr("thgs.pipeline.build_field", too_much)
    out = tmp_path / "x.thgs"
    code, _, err = run(["build", str(small_dataset), "-o", str(out)], capsys)
    assert code == 2 and "out of memory (Unable to allocate 99.1 GiB)" in err
    assert "Traceback" not in err and not out.exists()


@pytest.mark.slow
def test_field_rebuilds_from_its_record_to_the_same_bytes(
    small_dataset, small_field, tmp_path, capsys
):
    tuned = tmp_path / "tuned.thgs"
    code, _, err = run(
        [
            "build", str(small_dataset), "-o", str(tuned), "--preset", "3dovs",
            "--set", "merge.min_region_gaussians=40", "repeats.enabled=false",
        ],
        capsys,
    )  # fmt: skip
    assert code == 0, err
    recorded = recorded_config(load_field(tuned))
    assert recorded.merge.min_region_gaussians == 40 and not recorded.repeats.enabled
    assert recorded.features == FieldConfig.three_dovs().features

    again = tmp_path / "again.thgs"
    code, _, err = run(
        ["build", str(small_dataset), "-o", str(again), "--config", str(tuned)], capsys
    )
    assert code == 0, err
    assert again.read_bytes() == tuned.read_bytes()  # timings are not in the file

    as_json = tmp_path / "config.json"
    as_json.write_text(json.dumps(recorded.to_json()))
    assert read_field_config(as_json) == recorded
    code, _, err = run(
        ["build", str(small_dataset), "-o", str(tmp_path / "x.thgs"), "--config", str(as_json),
         "--preset", "lerf"],
        capsys,
    )  # fmt: skip
    assert code == 2 and "--preset: 'lerf' and --config both give every setting; pass one" in err
    assert not (tmp_path / "x.thgs").exists()


def test_a_field_recorded_before_min_support_was_built_without_it(small_field):
    field = load_field(small_field)
    recorded = recorded_config(field).merge
    assert recorded.min_support == MergeConfig().min_support > 0
    merge = {k: v for k, v in field.config["merge"].items() if k != "min_support"}
    older = dataclasses.replace(field, config={**field.config, "merge": merge})
    assert recorded_config(older).merge == dataclasses.replace(recorded, min_support=0.0)


def test_a_field_recorded_before_split_alternatives_was_partitioned_with_two(small_field):
    field = load_field(small_field)
    recorded = recorded_config(field).superpoints.partition
    assert recorded.split_alternatives == PartitionConfig().split_alternatives == 6
    superpoints = field.config["superpoints"]
    partition = {k: v for k, v in superpoints["partition"].items() if k != "split_alternatives"}
    older = dataclasses.replace(
        field, config={**field.config, "superpoints": {**superpoints, "partition": partition}}
    )
    assert recorded_config(older).superpoints.partition == dataclasses.replace(
        recorded, split_alternatives=2
    )
    assert "split_alternatives" in field.config["superpoints"]["partition"]  # record untouched


def test_a_field_recorded_before_polish_was_partitioned_without_it(small_field):
    field = load_field(small_field)
    recorded = recorded_config(field).superpoints.partition
    assert recorded.polish and PartitionConfig().polish
    superpoints = field.config["superpoints"]
    partition = {k: v for k, v in superpoints["partition"].items() if k != "polish"}
    older = dataclasses.replace(
        field, config={**field.config, "superpoints": {**superpoints, "partition": partition}}
    )
    assert recorded_config(older).superpoints.partition == dataclasses.replace(
        recorded, polish=False
    )


@pytest.mark.parametrize(
    ("setting", "ours", "before"),
    [
        ("median_steps", 2, 0),  # before it, the mean over views
        ("fit_power", 1.0, 0.0),  # before it, each view weighed by its visible share alone
    ],
)
def test_a_field_recorded_before_a_feature_setting_rebuilds_as_it_was(
    small_field, setting, ours, before
):
    field = load_field(small_field)
    recorded = recorded_config(field).features
    assert getattr(recorded, setting) == getattr(FeatureConfig(), setting) == ours
    features = {k: v for k, v in field.config["features"].items() if k != setting}
    older = dataclasses.replace(field, config={**field.config, "features": features})
    assert recorded_config(older).features == dataclasses.replace(recorded, **{setting: before})


def test_the_scene_is_found_relative_to_the_field(small_dataset, small_field, tmp_path):
    recorded = load_field(small_field).provenance.scene.path
    assert recorded == os.path.relpath(small_dataset, small_field.parent)
    # the field and its scene copied together elsewhere: the copy opens the copied scene
    root = small_field.parent.parent
    for original in (small_field, small_dataset):
        copy = tmp_path / original.relative_to(root)
        copy.parent.mkdir(parents=True, exist_ok=True)
        (shutil.copytree if original.is_dir() else shutil.copy)(original, copy)
    _, scene = open_field_scene(tmp_path / small_field.relative_to(root))
    assert scene.ply_path.resolve().is_relative_to(tmp_path.resolve())


def test_eval_renders_with_the_lifted_raster_settings(small_field):
    field = load_field(small_field)
    assert lifted_raster(field) == RasterConfig()
    tuned = dataclasses.replace(
        field,
        config={**field.config, "superpoints": {**field.config["superpoints"]}},
    )
    tuned.config["superpoints"]["lift"] = {
        **field.config["superpoints"]["lift"],
        "raster": {**field.config["superpoints"]["lift"]["raster"], "alpha_min": 0.01},
    }
    assert lifted_raster(tuned) == RasterConfig(alpha_min=0.01)


def test_an_unreadable_record_renders_with_defaults_and_says_so(small_field, caplog):
    field = load_field(small_field)
    odd = dataclasses.replace(field, config={**field.config, "merge": {"speed": 1}})
    with caplog.at_level("WARNING"):
        assert lifted_raster(odd, "odd.thgs") == RasterConfig()
    assert "odd.thgs: config.merge: unknown setting 'speed'" in caplog.text


def test_guidance_is_found_and_its_space_guessed(small_dataset, tmp_path):
    assert guidance_folder(small_dataset) == small_dataset / "language_features"
    assert guidance_folder(small_dataset / "point_cloud.ply") == small_dataset / "language_features"
    assert guidance_folder(tmp_path / "model", small_dataset) == small_dataset / "language_features"

    class View:
        def __init__(self, dim):
            self.features = np.zeros((2, dim), np.float32)

    assert guidance_space(tmp_path, [View(512)]) == LANGSPLAT_SPACE
    with pytest.raises(InputError, match=r"384-D features and no embedding\.json"):
        guidance_space(tmp_path, [View(384)])
    (tmp_path / "embedding.json").write_text('{"space": "my/space", "dim": 384}')
    assert guidance_space(tmp_path, [View(384)]) == "my/space"


def test_a_field_recorded_with_the_solver_thread_count_and_no_blocks_reads(small_field):
    field = load_field(small_field)
    recorded = recorded_config(field).superpoints.partition
    assert recorded.block_size == PartitionConfig().block_size > 0
    superpoints = field.config["superpoints"]
    partition = {k: v for k, v in superpoints["partition"].items() if k != "block_size"}
    older = dataclasses.replace(
        field,
        config={
            **field.config,
            "superpoints": {**superpoints, "partition": {**partition, "max_num_threads": 0}},
        },
    )
    assert recorded_config(older).superpoints.partition == dataclasses.replace(
        recorded, block_size=0
    )


def test_the_chosen_config_names_each_setting_once():
    assert chosen_field_config() == FieldConfig.lerf()
    assert chosen_field_config("3dovs") == FieldConfig.three_dovs()
    tuned = FieldConfig.lerf().with_settings(["merge.rounds=3"])
    assert chosen_field_config(config=tuned) == tuned
    # the authors' behaviour first, then --set: an explicit setting wins over --reference
    chosen = chosen_field_config(settings=["merge.rounds=5"], reference=True)
    assert chosen.merge.rounds == 5 and chosen.merge.two_hop_weight == 1.0
    assert chosen == dataclasses.replace(
        FieldConfig.lerf().as_reference(),
        merge=dataclasses.replace(FieldConfig.lerf().as_reference().merge, rounds=5),
    )
    assert not chosen_field_config(repeated_parts=False).repeats.enabled
    assert chosen_field_config(settings=[" repeats.enabled = false"]).repeats.enabled is False


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (
            {"settings": ["merge.rounds=2", "merge.rounds=3"]},
            "--set: names merge.rounds twice ('merge.rounds=2' and 'merge.rounds=3'); keep one",
        ),
        (
            {"settings": ["repeats.enabled=true"], "repeated_parts": False},
            "--no-repeated-parts: and --set 'repeats.enabled=true' both name repeats.enabled; "
            "keep one",
        ),
        (
            {"preset": "3dovs", "config": FieldConfig()},
            "--preset: '3dovs' and --config both give every setting; pass one",
        ),
        ({"preset": "lerff"}, "--preset: unknown 'lerff'; choose from lerf, 3dovs"),
    ],
)
def test_a_setting_named_twice_is_refused_naming_both(arguments, message):
    with pytest.raises(InputError) as caught:
        chosen_field_config(**arguments)
    assert str(caught.value) == message


def test_build_and_suite_refuse_a_setting_named_twice(small_dataset, tmp_path, capsys):
    out = tmp_path / "f.thgs"
    argv = ["build", str(small_dataset), "-o", str(out), "--no-repeated-parts"]
    code, _, err = run([*argv, "--set", "repeats.enabled=true"], capsys)
    assert code == 2 and "--no-repeated-parts: and --set 'repeats.enabled=true'" in err
    assert not out.exists()
    argv = ["suite", str(tmp_path), "-o", str(tmp_path / "o"), "--set", "merge.rounds=2"]
    code, _, err = run([*argv, "--set", "merge.rounds=3"], capsys)
    assert code == 2 and "--set: names merge.rounds twice" in err
    assert not (tmp_path / "o").exists()
