import pytest

from sara.config import config_from_dict, make_config, parse_override_args


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
    from sara.config import make_config

    conf = make_config("sift-offline", {"graph.loop_scale_fractions": "0.5,0.25,0.25"})
    assert conf.graph.loop_scale_fractions == (0.5, 0.25, 0.25)
    with pytest.raises(ValueError, match="graph.loop_scale_fractions"):
        make_config("sift-offline", {"graph.loop_scale_fractions": "0.5,x,0.25"})
