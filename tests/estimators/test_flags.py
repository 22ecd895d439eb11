"""The table of `udh estimate`'s typed flags: each an option some method takes, forwarded where -O goes."""

from __future__ import annotations

from pathlib import Path

from udh_cli.estimators.flags import OFF, OPTION_FLAGS, given_flags
from udh_cli.estimators.registry import estimator_names, nest_options, option_path


def test_every_flag_is_an_option_of_a_registered_method():
    for flag in OPTION_FLAGS:
        assert [name for name in estimator_names() if option_path(name, flag.key)], flag.key
    assert len({flag.key for flag in OPTION_FLAGS}) == len(OPTION_FLAGS) == 12


def test_given_flags_arrive_as_the_estimator_takes_them():
    values = {flag.key: None for flag in OPTION_FLAGS} | {"model": Path("m.onnx"), "flight_model": OFF.upper(), "search": 2, "tiles": False}
    assert given_flags(values) == {"model": "m.onnx", "flight_model": "", "search": 2, "tiles": False}
    # The same keys -O takes, nested where the method composes a record.
    assert nest_options("auto", given_flags(values)) == {"network": {"model": "m.onnx", "flight_model": "", "search": 2, "tiles": False}}
    assert nest_options("unsupervised", {"search": 2}, {"search": 1, "headings": 1}) == {"search": 2, "headings": 1}
