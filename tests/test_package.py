"""The package's front door: ``import udh_cli`` and ``udh_cli.estimators`` list every name they offer."""

from __future__ import annotations

import udh_cli
import udh_cli.estimators


def test_dir_lists_the_names_loaded_on_first_use_and_each_resolves():
    assert {"Estimator", "Estimate", "mosaic_images", "MosaicResult", "create_estimator"} <= set(dir(udh_cli))
    assert {"Estimator", "Estimate", "require_ok", "DEFAULT_METHOD"} <= set(dir(udh_cli.estimators))
    for module in (udh_cli, udh_cli.estimators):
        assert dir(module) == sorted(module.__all__)
        assert all(getattr(module, name) is not None for name in dir(module))
