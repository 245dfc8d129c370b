"""The stored F/T tare (``services/arm/ft_bias.py``) and how the reader takes it (``ft_reader.stored_tare``): a round
trip keeps every value, a missing file means untared, and a file that cannot be used is a clear, counted error,
never a zero bias."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from hydrosoft.services.arm.ft_bias import (
    MAX_FILE_BYTES,
    BiasFileError,
    StoredBias,
    bias_path,
    format_age,
    load_bias,
    save_bias,
)
from hydrosoft.services.ft_reader import stored_tare

PORT = "/dev/robotiq_ft300"


def stored(**changes) -> StoredBias:
    fields = dict(arm="bubble", port=PORT, bias=(1.25, -0.5, 3.125, 0.04, -0.03, 0.002),
                  taken_unix_ns=1_700_000_000_123_456_789, samples=50, source="ft tare")
    return StoredBias(**{**fields, **changes})


def test_a_saved_bias_loads_back_exactly_and_replaces_the_previous_one(tmp_path):
    path = bias_path(tmp_path / "state", "bubble")
    assert path == tmp_path / "state" / "ft_bias-bubble.json"
    save_bias(path, stored(bias=(9.0,) * 6))
    save_bias(path, stored())
    assert load_bias(path, "bubble", PORT) == stored()
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temporary file left behind
    np.testing.assert_array_equal(load_bias(path, "bubble", PORT).vector, [1.25, -0.5, 3.125, 0.04, -0.03, 0.002])


def test_no_file_means_no_bias(tmp_path):
    assert load_bias(tmp_path / "ft_bias-bubble.json", "bubble", PORT) is None
    current, error = stored_tare(tmp_path / "ft_bias-bubble.json", "bubble", PORT)
    assert current.bias is None and error is None
    assert "NOT TARED" in current.note() and "ft tare bubble" in current.note()


@pytest.mark.parametrize("content, reason", [
    (b"", "corrupt"),
    (b"{\"arm\": \"bubble\", \"port\"", "corrupt"),  # cut off mid-write
    (b"\x00\xff\x10garbage", "corrupt"),
    (json.dumps({"arm": "bubble", "port": PORT, "bias": [1, 2, 3], "taken_unix_ns": 1, "samples": 1,
                 "source": "x"}).encode(), "corrupt"),  # five numbers short
    (json.dumps({"arm": "bubble", "port": PORT, "bias": [1, 2, 3, 4, 5, "nan"], "taken_unix_ns": 1, "samples": 1,
                 "source": "x"}).encode(), "corrupt"),
    (b'{"arm": "bubble", "port": "/dev/robotiq_ft300", "bias": [0, 0, NaN, 0, 0, 0], "taken_unix_ns": 1, '
     b'"samples": 1, "source": "x"}', "corrupt"),
    (json.dumps({"arm": "bubble", "port": PORT, "bias": [0] * 6, "taken_unix_ns": 0, "samples": 1,
                 "source": "x"}).encode(), "corrupt"),  # no time
    (json.dumps({"arm": "bubble", "port": PORT, "bias": [0] * 6, "taken_unix_ns": 1, "samples": 1, "source": "x",
                 "extra": 1}).encode(), "corrupt"),
    (b" " * (MAX_FILE_BYTES + 1), "larger than"),
])
def test_a_corrupt_file_is_a_clear_error_and_never_a_zero_bias(tmp_path, content, reason):
    path = tmp_path / "ft_bias-bubble.json"
    path.write_bytes(content)
    with pytest.raises(BiasFileError, match=reason) as raised:
        load_bias(path, "bubble", PORT)
    assert str(path) in str(raised.value)
    current, error = stored_tare(path, "bubble", PORT)
    assert current.bias is None and current.stored is None  # untared, not zero
    assert error is not None and str(path) in error
    assert current.note().startswith("NOT TARED: stored bias unusable")


def test_a_bias_of_another_sensor_or_arm_is_refused(tmp_path):
    path = tmp_path / "ft_bias-bubble.json"
    save_bias(path, stored(port="/tmp/hydrosoft-sim/ft300-bubble"))  # a sim tare, read by the lab's reader
    with pytest.raises(BiasFileError, match="tare this sensor again"):
        load_bias(path, "bubble", PORT)
    save_bias(path, stored(arm="left"))
    with pytest.raises(BiasFileError, match="arm 'left'"):
        load_bias(path, "bubble", PORT)


def test_an_unreadable_file_is_an_error(tmp_path):
    path = tmp_path / "ft_bias-bubble.json"
    path.mkdir()  # a folder where the file should be
    with pytest.raises(BiasFileError, match="cannot be read"):
        load_bias(path, "bubble", PORT)


def test_the_note_shows_the_bias_its_time_and_its_age():
    now_ns = stored().taken_unix_ns + 150 * 10**9
    note = stored().describe(now_ns)
    assert note.startswith("tared: bias [1.250 -0.500 3.125 0.040 -0.030 0.002] N, N m, taken 2023-11-14 22:13:20 UTC")
    assert "(2.5 min ago, by ft tare)" in note
    assert [format_age(s) for s in (42.0, 3600.0 * 2, 86400.0 * 6.1)] == ["42 s", "2.0 h", "6.1 d"]
    assert 0 <= stored(taken_unix_ns=time.time_ns()).age_s() < 1.0
