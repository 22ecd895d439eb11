"""The exported model's metadata: portable paths, and the shipped models carry no machine's paths."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("torch")

from udh_cli.models_catalog import models_dir  # noqa: E402
from udh_cli.train.export import _portable_history, portable_path  # noqa: E402


def test_training_paths_are_kept_from_the_data_folder_on():
    assert portable_path("/home/me/shared/data/flights/seneca/images") == "data/flights/seneca/images"
    assert portable_path("../shared/data/pools/bsds500") == "data/pools/bsds500"
    assert portable_path("/work/runs/refine-tiles/best.pt") == "refine-tiles/best.pt"  # no data folder: the last two parts
    history = _portable_history({"init": "/work/runs/a/best.pt", "init_steps": 7, "init_data": ["/x/data/pools/p"]})
    assert history == {"init": "a/best.pt", "init_steps": 7, "init_data": ["data/pools/p"]}
    assert _portable_history({"init": "unsupervised"}) == {"init": "unsupervised"}  # a shipped model's name stays


def test_no_shipped_model_carries_an_absolute_path():
    onnx = pytest.importorskip("onnx")
    files = sorted(models_dir().glob("*.onnx"))
    assert files
    for path in files:
        metadata = {p.key: p.value for p in onnx.load(str(path), load_external_data=False).metadata_props}
        for key in ("training_data", "trained_before"):
            text = metadata.get(key, "")
            assert "/work/" not in text and '"/' not in text, (path.name, key, text[:80])
            json.loads(text or "{}")


def test_the_licence_given_is_recorded_and_an_export_without_one_records_none(tmp_path, monkeypatch, capfd):
    from conftest import export_tiny_network, run_main
    from udh_cli.onnx_model import OnnxHomographyModel
    from udh_cli.train.export import export_onnx

    plain = export_tiny_network(tmp_path, "corr", seed=0)
    assert "licence" not in OnnxHomographyModel.load(plain, "cpu").metadata
    result = export_onnx(tmp_path / "corr.pt", tmp_path / "licensed.onnx", licence="  CC BY 4.0;\n trained on CC0 images ")
    assert result["metadata"]["licence"] == "CC BY 4.0; trained on CC0 images"  # one line, as typed
    licensed = OnnxHomographyModel.load(tmp_path / "licensed.onnx", "cpu")
    assert licensed.licence == "CC BY 4.0; trained on CC0 images" and licensed.lacks() == []
    code, out, _ = run_main(monkeypatch, capfd, "export-onnx", str(tmp_path / "corr.pt"), "-o", str(tmp_path / "cli.onnx"),
                            "--licence", "research use only")
    assert code == 0 and OnnxHomographyModel.load(tmp_path / "cli.onnx", "cpu").licence == "research use only"
