"""The global solve stage returns its verdicts on the pairs: new records, the pairs it was given untouched."""

from __future__ import annotations

from types import SimpleNamespace

from udh_cli import geometry
from udh_cli.mosaic.pairs.types import PairResult
from udh_cli.mosaic.report import Reporter
from udh_cli.mosaic.solve.global_solve import GlobalSolve, solve_parts
from udh_cli.mosaic.solve.parts import chain_parts

SIZE = (320, 240)


def test_a_contradicted_loop_pair_comes_back_rejected_and_the_given_pairs_are_unchanged():
    ref_from = {i: geometry.translation(80.0 * i, 0.0) for i in range(6)}  # a straight strip, frame i 80 px right of i-1

    def pair(a: int, b: int, kind: str, shift_px: float = 0.0) -> PairResult:
        b_from_a = geometry.translation(shift_px, 0.0) @ geometry.invert(ref_from[b]) @ ref_from[a]
        return PairResult(a, b, kind, b_from_a=b_from_a / b_from_a[2, 2], status="ok")

    pairs = [pair(i, i + 1, "consecutive") for i in range(5)] + [pair(1, 3, "overlap"), pair(0, 2, "overlap", shift_px=40.0)]
    frameset = SimpleNamespace(frames=[SimpleNamespace(index=i, size=SIZE, name=f"f{i}.png") for i in range(6)])
    parts = chain_parts(frameset, pairs)

    solved = solve_parts(frameset, parts, pairs, GlobalSolve("homography", 2.0, 5.0, False, 3.0), Reporter(quiet=True))

    assert [p.status for p in solved.pairs] == ["ok"] * 6 + ["rejected"]
    assert solved.pairs[-1].b_from_a is None and solved.pairs[-1].reason.startswith("contradicted by the other pairs")
    assert solved.pairs[-1].consistency_px["after"] > 5.0 and solved.pairs[-1].consistency_px["loop"] is True
    assert solved.pairs[5].consistency_px["loop"] is True and solved.pairs[5].consistency_px["after"] < 0.01
    assert all(p.consistency_px["loop"] is False for p in solved.pairs[:5])
    assert all(p.status == "ok" and p.consistency_px == {} for p in pairs)  # the stage's input is left as it was
    assert solved.loops["loops_after"]["count"] == 1
