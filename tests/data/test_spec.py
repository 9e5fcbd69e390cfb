import re

import pytest

from dagr_lite.data.spec import SampleSpec
from dagr_lite.errors import UserError

SAMPLE = {"window_us": 33_333, "context_us": 10_000, "refractory_us": 0, "max_events": 100_000,
          "event_picture": False, "graph_context_us": 0, "carry_picture": False, "carry_recent_us": 0,
          "support_us": 0, "carry_confirm_us": 0, "carry_align_us": 0, "carry_spans_us": (), "carry_onset": False}


def test_a_sample_spec_round_trips_and_ignores_other_data_keys():
    spec = SampleSpec.from_dict({**SAMPLE, "image_age": 3, "clip_boxes": True})
    assert spec.as_dict() == SAMPLE and SampleSpec.from_dict(spec.as_dict()) == spec
    assert SampleSpec.keys() == tuple(SAMPLE)


@pytest.mark.parametrize(("key", "value", "expected"), [("window_us", 0, "a positive integer"),
                                                        ("context_us", -1, "an integer >= 0"),
                                                        ("refractory_us", 2.5, "an integer >= 0"),
                                                        ("max_events", 0, "a positive integer or None"),
                                                        ("event_picture", "no", "true or false"),
                                                        ("carry_recent_us", -5, "an integer >= 0"),
                                                        ("support_us", -1, "an integer >= 0"),
                                                        ("carry_confirm_us", -1, "an integer >= 0"),
                                                        ("carry_align_us", -1, "an integer >= 0"),
                                                        ("carry_spans_us", (5, 5), "a tuple of increasing positive integers"),
                                                        ("carry_spans_us", (0,), "a tuple of increasing positive integers"),
                                                        ("carry_spans_us", "33333", "a tuple of increasing positive integers"),
                                                        ("carry_onset", 1, "true or false")])
def test_a_bad_value_is_named(key, value, expected):
    with pytest.raises(UserError, match=re.escape(f"sample {key} must be {expected}, got {value!r}")):
        SampleSpec(**{**SAMPLE, key: value})


def test_a_configs_list_of_spans_is_a_tuple():
    spec = SampleSpec(**{**SAMPLE, "carry_spans_us": [33_333, 66_667]})
    assert spec.carry_spans_us == (33_333, 66_667) and SampleSpec.from_dict(spec.as_dict()) == spec


def test_a_missing_key_is_named():
    with pytest.raises(UserError, match=r"a sample spec needs \['refractory_us'\]"):
        SampleSpec.from_dict({key: v for key, v in SAMPLE.items() if key != "refractory_us"})
