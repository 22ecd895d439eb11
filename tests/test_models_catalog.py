"""The shipped models' catalogue (udh_cli.models_catalog) against what an installed package carries."""

from __future__ import annotations

import tomllib
from pathlib import Path

from udh_cli import models_catalog

ROOT = Path(__file__).resolve().parents[1]


def test_every_shipped_run_is_installed_with_the_package():
    # A wheel carries only the files package-data names; a run's weights left out would make
    # `udh train --init unsupervised-flight` fail for everyone who did not install from a clone.
    patterns = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["udh_cli.models"]
    for name, relative in models_catalog.SHIPPED_RUNS.items():
        assert relative in patterns, name
        assert (ROOT / "models" / relative).is_file(), name
        assert models_catalog.shipped_checkpoint(name) == models_catalog.models_dir() / relative


def test_every_shipped_network_records_its_sets_licence_and_lacks_no_metadata():
    from udh_cli.onnx_model import OnnxHomographyModel, OnnxMatcher

    assert set(models_catalog.SHIPPED_LICENCE) == set(models_catalog.SHIPPED_MODELS)
    for name, licence in models_catalog.SHIPPED_LICENCE.items():
        precisions = ("fp32", "int8") if name in models_catalog.SHIPPED_INT8 else ("fp32",)
        for precision in precisions:
            path = models_catalog.shipped_onnx(name, precision)
            network = (OnnxMatcher if name.endswith("-matcher") else OnnxHomographyModel).load(path, "cpu")
            assert network.licence == models_catalog.WEIGHTS_LICENCES[licence], path.name
            assert network.lacks() == [], path.name


def test_the_help_names_each_sets_terms_and_the_methods_that_run_it():
    text = models_catalog.licence_help()
    for key in set(models_catalog.SHIPPED_LICENCE.values()):
        assert models_catalog.WEIGHTS_LICENCES[key] in text
    assert "unsupervised (also inside auto)" in text and "supervised" in text.replace("unsupervised", "")
