"""The configuration: overrides, presets, the rules beside the fields, renamed keys, the generated docs."""

import dataclasses
import logging
from pathlib import Path

import pytest

from sara import config as sara_config
from sara.config import (
    RENAMED,
    ConfigError,
    PipelineConfig,
    apply_overrides,
    config_from_dict,
    make_config,
    parse_override_args,
)


def test_overrides_are_typed():
    conf = make_config("sift-offline", {"retrieval.num_neighbors": "7", "score.alpha": "0.5",
                                        "images.recursive": "true", "pairs.method": "exhaustive"})
    assert conf.retrieval.num_neighbors == 7
    assert conf.score.alpha == 0.5
    assert conf.images.recursive is True
    assert conf.pairs.method == "exhaustive"


def test_unknown_key_lists_valid_ones():
    with pytest.raises(ValueError, match="unknown option 'retrieval.nope'.*retrieval.num_neighbors"):
        make_config("sift-offline", {"retrieval.nope": "1"})


def test_bad_value_and_group():
    with pytest.raises(ValueError, match="not a int"):
        make_config("sift-offline", {"retrieval.num_neighbors": "many"})
    with pytest.raises(ValueError, match="group of options"):
        make_config("sift-offline", {"retrieval": "1"})


def test_unknown_preset():
    with pytest.raises(ValueError, match="unknown preset"):
        make_config("nope")


def test_roundtrip_through_dict():
    conf = make_config("sift-fast", {"graph.use_loops": "false", "seed": "3"})
    assert config_from_dict(conf.to_dict()) == conf


def test_parse_override_args():
    assert parse_override_args(["a.b=1", "c = x"]) == {"a.b": "1", "c": "x"}
    with pytest.raises(ValueError, match="key=value"):
        parse_override_args(["oops"])


def test_tuple_options_are_set_with_commas() -> None:
    conf = make_config("sift-offline", {"graph.loop_scale_fractions": "0.5,0.25,0.25"})
    assert conf.graph.loop_scale_fractions == (0.5, 0.25, 0.25)
    with pytest.raises(ValueError, match="graph.loop_scale_fractions"):
        make_config("sift-offline", {"graph.loop_scale_fractions": "0.5,x,0.25"})


# --- the sections, the rules beside the fields, the renamed keys, the generated reference ---------


def _option_fields(conf, prefix=""):
    for f in dataclasses.fields(conf):
        value = getattr(conf, f.name)
        if dataclasses.is_dataclass(value):
            yield from _option_fields(value, f"{prefix}{f.name}.")
        else:
            yield prefix + f.name, f


def test_every_field_has_its_rule_advanced_flag_and_description_beside_it():
    options = dict(_option_fields(PipelineConfig()))
    for key, f in options.items():
        check, valid = f.metadata["rule"]
        assert callable(check) and valid, key
        assert isinstance(f.metadata["advanced"], bool), key
        assert f.metadata["doc"] and "docs/" not in f.metadata["doc"], key
    assert sorted(sara_config.RULES) == sorted(options)  # RULES is read from the fields


def test_every_default_passes_its_rule_and_an_out_of_range_value_is_a_config_error():
    for key, f in _option_fields(PipelineConfig()):
        value = PipelineConfig()
        for part in key.split("."):
            value = getattr(value, part)
        assert f.metadata["rule"][0](value), key
    for key, bad in [("budget.max_pairs_fraction", 1.5), ("rounds.repair_rounds", -1), ("sequential.overlap", 0),
                     ("vocab_tree.num_words", 1), ("graph.loop_scale_fractions", (1.0, 2.0)), ("seed", -3)]:
        with pytest.raises(ConfigError, match=key.replace(".", r"\.")) as caught:
            make_config(overrides={key: bad})
        assert caught.value.option == key


def test_old_keys_on_the_command_line_set_the_new_ones_with_a_warning(caplog):
    with caplog.at_level(logging.WARNING, logger="sara.config"):
        conf = make_config("sift-offline", parse_override_args(["graph.densify=true", "pairs.min_view_inliers=7"]))
    assert conf.budget.densify is True and conf.rounds.support_min_view_inliers == 7
    warned = [r.getMessage() for r in caplog.records]
    assert len(warned) == 2 and "'budget.densify'" in warned[0] and "'rounds.support_min_view_inliers'" in warned[1]
    with pytest.raises(ValueError, match="old name"):
        make_config(overrides={"graph.densify": "true", "budget.densify": "false"})


def test_every_old_key_names_an_existing_option():
    options = dict(_option_fields(PipelineConfig()))
    assert len(RENAMED) == 24
    for old, new in RENAMED.items():
        assert new in options and old not in options, old
        default = apply_overrides(PipelineConfig(), {new: _default(new)})
        assert apply_overrides(PipelineConfig(), {old: _default(new)}) == default


def _default(key):
    value = PipelineConfig()
    for part in key.split("."):
        value = getattr(value, part)
    return value


#: options added after the old layout, which its files never hold (their defaults apply)
NEWER_THAN_THE_OLD_LAYOUT = ("max_time_fraction", "repair_descriptor_ratio", "fill_before_map_images",
                             "pose_guided_last")


def test_a_run_json_of_the_old_layout_still_loads():
    conf = make_config("aliked-lightglue", {"budget.densify": "true", "sequential.overlap": "4",
                                            "vocab_tree.num_images": "9", "rounds.extend_model": "false"})
    old = conf.to_dict()
    for section in ("sequential", "vocab_tree", "budget", "rounds"):
        for name, value in old.pop(section).items():
            new = f"{section}.{name}"
            former = next((o for o, n in RENAMED.items() if n == new), None)
            if former is None:  # an option added after the layout changed: absent from old files
                assert section == "rounds" and name in NEWER_THAN_THE_OLD_LAYOUT, new
                continue
            head, _, field_name = former.partition(".")
            old[head][field_name] = value
    assert "densify" in old["graph"] and "extend_model" in old["map"] and "sequential_overlap" in old["pairs"]
    assert config_from_dict(old) == conf
    with pytest.raises(ValueError, match="unknown option 'graph.nope'"):
        config_from_dict({**old, "graph": {**old["graph"], "nope": 1}})


def test_budget_caps_keep_their_arithmetic():
    budget = sara_config.BudgetConfig()
    assert [budget.pair_cap(n) for n in (3, 11, 47)] == [2, 13, 188]
    assert [budget.densify_cap(n) for n in (11, 47)] == [33, 8 * 47]
    assert budget.total_cap(47) == 188
    assert dataclasses.replace(budget, densify=True).total_cap(47) == 8 * 47


def test_everyday_keys_are_few_and_the_paper_constants_advanced():
    everyday = sara_config.everyday_keys()
    assert 8 <= len(everyday) <= 14
    assert {"pairs.method", "extract.backend", "budget.max_pairs_per_image", "map.mapper"} <= set(everyday)
    assert not [k for k in everyday if k.split(".")[0] in ("score", "graph", "rounds")]


def test_docs_configuration_md_is_the_generated_reference():
    path = Path(__file__).resolve().parents[1] / "docs" / "configuration.md"
    regenerate = sara_config.describe.REGENERATE
    assert path.is_file(), f"docs/configuration.md is missing; regenerate it from the repository root: {regenerate}"
    assert path.read_text(encoding="utf-8") == sara_config.describe_markdown(), (
        f"docs/configuration.md differs from the configuration; regenerate it from the repository root: {regenerate}")
    text = path.read_text(encoding="utf-8")
    assert text.index("## Everyday keys") < text.index("## Advanced keys")
    for key in sara_config.RULES:
        assert f"`{key}`" in text, key
