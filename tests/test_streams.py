"""Named random streams: one place, the same numbers as the arithmetic they replaced."""

import doctest

import pytest

from bluesky_offsets import streams
from bluesky_offsets.errors import InputError


def test_the_module_examples_run():
    assert doctest.testmod(streams).failed == 0


def test_the_streams_keep_the_seeds_they_had():
    assert streams.stream(3, "demo.hidden_offsets") == 4 and streams.stream(3, "demo.ioc_noise") == 5
    assert streams.stream(3, "demo.beam_optimizer") == 14 and streams.stream(0, "diagnosis.fits") == 7919
    assert [streams.stream(0, "diagnosis.fresh_rays", draw=d) for d in (0, 1)] == [104729, 209458]
    assert streams.MODEL_SEED == 777
    with pytest.raises(InputError, match="no random stream"):
        streams.stream(0, "demo.typo")
