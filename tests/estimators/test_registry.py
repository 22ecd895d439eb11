"""The registry's options: a composed record's keys reached dotted (network.search), bare, or whole."""

from __future__ import annotations

import pytest

from udh_cli.errors import UdhError
from udh_cli.estimators import create_estimator
from udh_cli.estimators.refined import NETWORK_DEFAULTS
from udh_cli.estimators.registry import (estimator_options, nest_options, option_path, parse_method_options,
                                         with_option_default)


def test_a_dotted_key_reaches_the_composed_record():
    got = parse_method_options(["network.search=2", "auto.network.model=my.onnx", "fallback=orb"], ["auto"])
    assert got == {"auto": {"network": {"search": 2, "model": "my.onnx"}, "fallback": "orb"}}
    assert option_path("auto", "network.search") == ("network", "search")
    assert "network.search" in estimator_options("auto") and "search" not in estimator_options("auto")


def test_a_flat_key_of_before_maps_to_the_same_nested_value():
    for flat, nested in ((["search=2"], ["network.search=2"]), (["auto.tiles=true"], ["auto.network.tiles=true"])):
        assert parse_method_options(flat, ["auto"]) == parse_method_options(nested, ["auto"])
    assert nest_options("auto", {"threads": 1, "min_score": 0.6}) == {"network": {"threads": 1}, "min_score": 0.6}
    assert nest_options("auto", {"network": {"search": 1}, "iterations": 2}) == {"network": {"search": 1, "iterations": 2}}
    # A method's own field comes first: unsupervised takes search itself.
    assert option_path("unsupervised", "search") == ("search",) and option_path("sift", "search") is None


def test_an_unknown_dotted_key_is_one_line_naming_the_valid_keys():
    with pytest.raises(UdhError, match=r"'network.serch'.*auto's network takes: model, device, .*search, ") as caught:
        parse_method_options(["network.serch=2"], ["auto"])
    assert "\n" not in str(caught.value)
    with pytest.raises(UdhError, match=r"auto's network takes: .*threads$"):
        parse_method_options(["network.judged=false"], ["auto"])  # the cascade judges its answers itself
    with pytest.raises(UdhError, match=r"does not take network.colour; auto's network takes: model"):
        nest_options("auto", {"network": {"colour": True}})
    with pytest.raises(UdhError, match=r"no method here takes 'serch'.*auto takes: initial, network.\{model, device"):
        parse_method_options(["serch=2"], ["auto"])


def test_a_default_goes_where_the_method_takes_it_unless_given():
    assert with_option_default("auto", {}, "search", 2) == {"network": {"search": 2}}
    assert with_option_default("auto", {"network.search": 0}, "search", 2) == {"network": {"search": 0}}
    assert with_option_default("unsupervised", {"search": None}, "search", 2) == {"search": None}
    assert with_option_default("unsupervised", {"threads": None}, "threads", 1, none_is_unset=True) == {"threads": 1}
    assert with_option_default("sift", {"ratio": 0.8}, "search", 2) == {"ratio": 0.8}


def test_the_network_options_reach_the_start_network():
    dotted = create_estimator("unsupervised+ecc", device="cpu", **{"network.search": 3, "network.threads": 1})
    flat = create_estimator("unsupervised+ecc", device="cpu", search=3, threads=1)
    assert dotted.start.search == flat.start.search == 3 and dotted.start.threads == 1
    assert dotted.settings() == flat.settings()
    plain = create_estimator("unsupervised+ecc", device="cpu")
    assert (plain.start.iterations, plain.start.search, plain.start.tiles) == tuple(NETWORK_DEFAULTS[k] for k in ("iterations", "search", "tiles"))
    assert plain.start.judged is False
    with pytest.raises(UdhError, match=r"method 'unsupervised\+ecc', its network: .*search takes int or none"):
        create_estimator("unsupervised+ecc", device="cpu", search="two")
    with pytest.raises(UdhError, match="network takes the network's options"):
        create_estimator("unsupervised+ecc", network="search=2")


def test_a_flag_and_an_option_that_set_one_setting_differently_are_refused():
    """``--search 2 -O network.search=3``: neither may silently win; the same value twice, or different settings, merge."""
    from udh_cli.estimators.registry import merge_flag_options

    options = parse_method_options(["network.search=3"], ["auto"])["auto"]
    with pytest.raises(UdhError, match=r"network\.search is given twice, as --search 2 and -O network\.search=3"):
        merge_flag_options("auto", {"search": 2}, options)
    assert merge_flag_options("auto", {"search": 3}, options) == {"network": {"search": 3}}
    assert merge_flag_options("auto", {"search": 2}, {"min_score": 0.5}) == {"min_score": 0.5, "network": {"search": 2}}
    with pytest.raises(UdhError, match="search is given twice"):
        merge_flag_options("unsupervised", {"search": 2}, {"search": 3})
