"""The learned estimators' networks (estimators/networks.py): one record by role, loaded by one function."""

from __future__ import annotations

from pathlib import Path

import pytest

from conftest import export_tiny_network
from udh_cli.errors import UdhError
from udh_cli.estimators.networks import load_networks
from udh_cli.models_catalog import SHIPPED_MODELS, ShippedRoles, has_refinement_stage


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> tuple[Path, Path]:
    """A coarse and a refinement network, untrained, 32 px."""
    return (export_tiny_network(tmp_path_factory.mktemp("coarse"), "corr", seed=0),
            export_tiny_network(tmp_path_factory.mktemp("fine"), "corr-fine", seed=1))


def load(coarse, refine_rounds=0, tiles=False, **files):
    options = dict(refine_model=None, rounds_model=None, tile_coarse_model=None, flight_model="", matcher_model="") | files
    return load_networks("unsupervised", model=str(coarse), refine_rounds=refine_rounds, tiles=tiles, precision=None, device="cpu",
                         threads=1, **options)


def test_a_network_alone_runs_every_role_of_the_cascade(tiny):
    coarse, _ = tiny
    networks = load(coarse)
    assert networks.coarse.path == coarse and networks.tile is networks.coarse
    assert (networks.rounds, networks.tile_coarse, networks.flight, networks.matcher) == (None, None, None, None)
    assert networks.first == [networks.coarse] and networks.side == 32
    assert networks.files() == [str(coarse)] and networks.precision() == "fp32"


def test_a_refinement_network_runs_the_rounds_and_the_tiles_and_the_coarse_one_the_tiles_coarse_level(tiny):
    coarse, fine = tiny
    networks = load(coarse, refine_rounds=2, refine_model=str(fine))
    assert networks.rounds is networks.tile and networks.tile.path == fine and networks.tile_coarse is networks.coarse
    with_rounds = load(coarse, refine_rounds=2, refine_model=str(fine), rounds_model=str(coarse), flight_model=str(coarse))
    assert with_rounds.rounds.path == coarse and with_rounds.tile.path == fine
    assert [n.path for n in with_rounds.first] == [coarse, coarse]
    assert with_rounds.files() == sorted({str(coarse), str(fine)})


def test_the_tiles_coarse_network_needs_a_refinement_stage(tiny):
    coarse, _ = tiny
    with pytest.raises(UdhError, match="tile_coarse_model runs in the tile stage, which needs a refinement stage"):
        load(coarse, tile_coarse_model=str(coarse))


def test_every_shipped_role_is_a_catalogue_name_and_the_supervised_method_has_no_refinement_stage():
    roles = ShippedRoles.of("unsupervised")
    assert {roles.coarse, roles.refine, roles.flight, roles.matcher} <= set(SHIPPED_MODELS)
    assert ShippedRoles.of("supervised").refine not in SHIPPED_MODELS
    assert not has_refinement_stage("supervised", None, None) and has_refinement_stage("supervised", None, "fine.onnx")


def _with_metadata(source: Path, target: Path, drop: tuple[str, ...] = (), **extra: str) -> Path:
    """A copy of the ONNX file ``source`` with the metadata keys ``drop`` removed and ``extra`` set."""
    onnx = pytest.importorskip("onnx")
    from udh_cli.onnx_model import write_metadata

    proto = onnx.load(str(source))
    metadata = {p.key: p.value for p in proto.metadata_props if p.key not in drop} | extra
    write_metadata(proto, metadata)
    target.write_bytes(proto.SerializeToString())
    return target


def test_a_file_without_a_licence_or_headings_loads_with_a_note_of_what_it_lacks(tiny, tmp_path):
    coarse, fine = tiny
    assert load(coarse).notes() == ["corr.onnx: records no licence for its weights; check the terms of the images it was trained "
                                    "on before using its answers (re-export it with `udh export-onnx --licence TEXT`)"]
    old = _with_metadata(coarse, tmp_path / "old.onnx", drop=("max_heading",))
    networks = load(old, refine_rounds=2, refine_model=str(fine))
    assert [line.split(": ")[0] for line in networks.notes()] == ["old.onnx", "old.onnx", "corr-fine.onnx"]
    assert "taken as trained without turns" in networks.notes()[1]
    licensed = _with_metadata(coarse, tmp_path / "licensed.onnx", licence="CC BY 4.0")
    assert load(licensed).notes() == [] and load(licensed).coarse.licence == "CC BY 4.0"
    assert load(coarse).coarse.licence is None
    twice = load(coarse, refine_rounds=2, refine_model=str(coarse), flight_model=str(coarse))
    assert len(twice.notes()) == 1  # one file in three roles: one note
