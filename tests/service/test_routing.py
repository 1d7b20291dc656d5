"""The scoring routes' JSON parser (service/routing.py): pydantic-core where it accepts, the standard parser
where it refuses -- the same Python objects as ``json.loads`` on every body both accept, and the standard
parser's answer (or error) on the rest."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service.routing import parse_json

AGREE = [
    b'{"plan": [[0.1, 1e-310, 5e-324, 1.7976931348623157e308, -0.0, 0.30000000000000004]]}',  # the last bit
    b'{"a": 1, "a": 2}',  # duplicate keys: the last wins
    b'{"n": 9223372036854775807, "m": -9223372036854775808}',  # the 64-bit ends
    b'{"n": 123456789012345678901234567890}',  # beyond 64 bits: exact, not a float
    '{"s": "caf\u00e9 \u2603 \\u00e9 \\ud83d\\ude00"}'.encode(),  # unicode, escapes, a surrogate pair
    b'[1, 2.5, true, false, null, "x", {"k": []}]',
    b'  {"padded": 1}  \n',
]
STANDARD_DECIDES = [
    b'{"x": NaN}', b'{"x": Infinity}', b'{"x": -Infinity}',  # not JSON, yet accepted by json.loads
    b'{"s": "\\ud800"}',  # a lone surrogate escape
]
REFUSED = [b'{"plan": [1, 2,]}', b'{"a": 1', b'', b'{"a": 1} extra', b"{'a': 1}"]


@pytest.mark.parametrize("body", AGREE)
def test_where_both_accept_they_agree(body):
    assert parse_json(body) == json.loads(body)
    assert repr(parse_json(body)) == repr(json.loads(body))  # floats to the last bit, -0.0 included


@pytest.mark.parametrize("body", STANDARD_DECIDES)
def test_what_only_the_standard_parser_accepts_it_decides(body):
    got, expected = parse_json(body), json.loads(body)
    assert repr(got) == repr(expected) or (math.isnan(got["x"]) and math.isnan(expected["x"]))


@pytest.mark.parametrize("body", REFUSED)
def test_refusals_are_the_standard_parsers_with_its_offsets(body):
    with pytest.raises(json.JSONDecodeError) as ours:
        parse_json(body)
    with pytest.raises(json.JSONDecodeError) as standard:
        json.loads(body)
    assert (ours.value.msg, ours.value.pos) == (standard.value.msg, standard.value.pos)


@settings(max_examples=50, deadline=None)
@given(st.integers(1, 4), st.integers(8, 20), st.integers(0, 2**32 - 1))
def test_random_plan_bodies_parse_alike(n, t, seed):
    plans = np.random.default_rng(seed).normal(0.0, 3.0, (n, t, 16)).tolist()
    body = json.dumps({"image": "aGVsbG8=", "plans": plans, "task": "stacking"}).encode()
    assert parse_json(body) == json.loads(body)
