"""The examples in the protocol's docstrings (CRC check value, CAN identifiers, capacity) run."""

import doctest
import importlib

import pytest

MODULES = ["protocol.crc", "protocol.can", "protocol.capacity", "protocol.constants", "protocol.lattice",
           "protocol.messages"]


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    result = doctest.testmod(importlib.import_module(name))
    assert result.attempted > 0 and result.failed == 0
