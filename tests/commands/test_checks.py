"""The command-line checks shared by the commands."""

import pytest

from vcfusion.commands.checks import parse_seeds


def test_parse_seeds():
    assert parse_seeds("0-3") == [0, 1, 2, 3]
    assert parse_seeds("5,1,2-3") == [1, 2, 3, 5]
    for bad in ("a", "3-1", "-2", ""):
        with pytest.raises(ValueError, match="--seeds"):
            parse_seeds(bad)
